//! Interface declarations: what a device publishes on `fbbus/declare/<device>` at birth
//! (`Declaration::from_json` + `validate`, as `broker/src/policy/typed.rs` does), the type
//! names in them (`DataType::from_str`), and typed interfaces read back from JSON (how the
//! device registry file and other lines' records hold them).
//!
//! Checks: nothing panics; a validated interface serializes to JSON that declares the same
//! interface again; every output it lists resolves, with every WITH port typed; every
//! type that parses prints as text that parses to the same type.
#![no_main]

use fb_bridge::interface::{is_identifier, Declaration, Interface, OutputPort};
use fb_bridge::types::{DataType, ElementaryType};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        type_names(text);
        for line in text.lines().take(8) {
            type_names(line);
        }
    }
    // The registry's form: types already parsed (`DataType`'s `Deserialize`).
    if let Ok(typed) = serde_json::from_slice::<Interface>(data) {
        let json = serde_json::to_vec(&typed).unwrap();
        let again: Interface = serde_json::from_slice(&json).expect("a typed interface reads back");
        assert_eq!(again, typed);
    }

    let Ok(declaration) = Declaration::from_json(data) else {
        return;
    };
    let Ok(interface) = declaration.validate() else {
        return;
    };
    for (fb, i) in &interface.fbs {
        assert!(is_identifier(fb), "FB {fb:?} validated");
        for port in i.events_out.keys().chain(i.data_out.keys()) {
            assert!(is_identifier(port), "port {fb}.{port} validated");
        }
    }
    let outputs: Vec<(String, String)> = interface
        .outputs()
        .map(|(f, p)| (f.to_owned(), p.to_owned()))
        .collect();
    for (fb, port) in &outputs {
        match interface.output(fb, port) {
            Some(OutputPort::Data(_)) => {}
            Some(OutputPort::Event(with)) => {
                let declared = &interface.fbs[fb].events_out[port].with;
                assert_eq!(
                    with.len(),
                    declared.len(),
                    "{fb}.{port}: every WITH port of a validated event has a type"
                );
            }
            None => panic!("listed output {fb}.{port} does not resolve"),
        }
    }
    // Serialized (the registry record, the bus) and declared again: the same interface.
    let json = serde_json::to_vec(&interface).unwrap();
    let again = Declaration::from_json(&json)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&json)))
        .validate()
        .unwrap_or_else(|e| panic!("{e:?}: {}", String::from_utf8_lossy(&json)));
    assert_eq!(again, interface);
});

/// A type name parses to at most one type, and that type's name parses to it again.
fn type_names(text: &str) {
    if let Ok(t) = text.parse::<ElementaryType>() {
        assert_eq!(t.name().parse::<ElementaryType>(), Ok(t));
        assert_eq!(ElementaryType::from_number(t.number()), Some(t));
    }
    if let Ok(t) = text.parse::<DataType>() {
        let shown = t.to_string();
        assert_eq!(shown.parse::<DataType>(), Ok(t), "{text:?} -> {shown:?}");
        if let DataType::Array(_, n) = t {
            assert!(n >= 1, "{text:?}: an empty array");
        }
    }
}
