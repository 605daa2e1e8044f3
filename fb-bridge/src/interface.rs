//! A device's FB interface: what it declares at birth, and how the broker checks it.
//!
//! A declaration names the device's FB instances and, per FB, its event outputs and
//! inputs (each with its IEC 61499 WITH list) and its data outputs and inputs with their
//! types. Outputs are what the device publishes (`fb/<device>/<fb>/<port>`); inputs are
//! what it consumes, declared so the registry shows the whole interface.
//!
//! Parsing keeps types as text ([`Declaration`]) so that [`Declaration::validate`] can
//! report every mistake at once, each with its FB and port, instead of stopping at the
//! first bad type the way a typed deserializer would.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::types::{DataType, ElementaryType};

/// An interface as sent by a device: types still as text.
pub type Declaration = Interface<String>;

/// A device's FB instances by name.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(
    deny_unknown_fields,
    bound(deserialize = "T: Deserialize<'de>", serialize = "T: Serialize")
)]
pub struct Interface<T = DataType> {
    pub fbs: BTreeMap<String, FbInterface<T>>,
}

/// One FB instance's interface.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(
    deny_unknown_fields,
    bound(deserialize = "T: Deserialize<'de>", serialize = "T: Serialize")
)]
pub struct FbInterface<T = DataType> {
    /// The FB's type name (`CONVEYOR`, `E_CYCLE`, ...); informative.
    #[serde(rename = "type", default, skip_serializing_if = "Option::is_none")]
    pub fb_type: Option<String>,
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub events_out: BTreeMap<String, Event>,
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub events_in: BTreeMap<String, Event>,
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub data_out: BTreeMap<String, T>,
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub data_in: BTreeMap<String, T>,
}

/// An event port: the data ports whose values it carries (IEC 61499 WITH), in order.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Event {
    #[serde(default)]
    pub with: Vec<String>,
}

/// One mistake in a declaration, located precisely.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, thiserror::Error)]
#[error("{}{}{error}", fb.as_ref().map(|f| format!("FB {f}: ")).unwrap_or_default(), port.as_ref().map(|p| format!("port {p}: ")).unwrap_or_default())]
pub struct DeclarationError {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fb: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub port: Option<String>,
    pub error: String,
}

/// Most FBs a device may declare, and most ports per FB: bounds what one birth costs.
pub const MAX_FBS: usize = 256;
pub const MAX_PORTS: usize = 256;

/// The first key that appears twice in one JSON object of `payload` (valid JSON), if any.
fn duplicate_key(payload: &[u8]) -> Option<String> {
    use serde::de::{DeserializeSeed, MapAccess, SeqAccess, Visitor};

    struct Walk<'a>(&'a mut Option<String>);

    impl<'de> DeserializeSeed<'de> for Walk<'_> {
        type Value = ();
        fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
            d.deserialize_any(self)
        }
    }

    impl<'de> Visitor<'de> for Walk<'_> {
        type Value = ();
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("JSON")
        }
        fn visit_bool<E>(self, _: bool) -> Result<(), E> {
            Ok(())
        }
        fn visit_i64<E>(self, _: i64) -> Result<(), E> {
            Ok(())
        }
        fn visit_u64<E>(self, _: u64) -> Result<(), E> {
            Ok(())
        }
        fn visit_f64<E>(self, _: f64) -> Result<(), E> {
            Ok(())
        }
        fn visit_str<E>(self, _: &str) -> Result<(), E> {
            Ok(())
        }
        fn visit_unit<E>(self) -> Result<(), E> {
            Ok(())
        }
        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
            let found = self.0;
            while seq.next_element_seed(Walk(&mut *found))?.is_some() {}
            Ok(())
        }
        fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
            let found = self.0;
            let mut seen = std::collections::HashSet::new();
            while let Some(key) = map.next_key::<String>()? {
                if found.is_none() && seen.contains(&key) {
                    *found = Some(key);
                } else {
                    seen.insert(key);
                }
                map.next_value_seed(Walk(&mut *found))?;
            }
            Ok(())
        }
    }

    let mut found = None;
    let mut de = serde_json::Deserializer::from_slice(payload);
    let _ = Walk(&mut found).deserialize(&mut de);
    found
}

/// An IEC 61131-3 identifier: a letter or `_`, then letters, digits and `_`. Names become
/// topic levels, so this also keeps `/`, `+`, `#` and `$` out of them.
pub fn is_identifier(name: &str) -> bool {
    let mut chars = name.chars();
    matches!(chars.next(), Some(c) if c.is_ascii_alphabetic() || c == '_')
        && chars.all(|c| c.is_ascii_alphanumeric() || c == '_')
        && name.len() <= 64
}

impl Declaration {
    /// Parses a birth payload (JSON). Syntax errors say where they are.
    pub fn from_json(payload: &[u8]) -> Result<Declaration, DeclarationError> {
        let declaration = serde_json::from_slice(payload).map_err(|e| DeclarationError {
            fb: None,
            port: None,
            error: format!("not a valid interface declaration: {e}"),
        })?;
        // serde keeps the last of two equal keys: a declaration naming an FB or a port twice
        // would silently lose one (issue 21). Refused instead.
        if let Some(key) = duplicate_key(payload) {
            return Err(DeclarationError {
                fb: None,
                port: None,
                error: format!(
                    "`{key}` appears twice in one JSON object: every FB, port and key is \
                     named once"
                ),
            });
        }
        Ok(declaration)
    }

    /// The ports declared, over every FB: event and data, outputs and inputs.
    pub fn port_count(&self) -> usize {
        self.fbs
            .values()
            .map(|fb| {
                fb.events_out.len() + fb.events_in.len() + fb.data_out.len() + fb.data_in.len()
            })
            .sum()
    }

    /// Checks every FB and port and returns the typed interface, or every mistake found.
    pub fn validate(self) -> Result<Interface, Vec<DeclarationError>> {
        match self.validate_partly()? {
            (interface, errors) if errors.is_empty() => Ok(interface),
            (_, errors) => Err(errors),
        }
    }

    /// Checks every FB and port: the typed interface of what is right (an FB whose name or
    /// port count is wrong is left out, and so is a data port whose type is), with every
    /// mistake found. For a caller that goes on checking what refers to the interface (a
    /// profile's topics), so that one run reports every mistake. Err: the declaration is
    /// refused as a whole (too many FBs).
    pub fn validate_partly(
        self,
    ) -> Result<(Interface, Vec<DeclarationError>), Vec<DeclarationError>> {
        let mut errors = Vec::new();
        let mut err = |fb: &str, port: Option<&str>, error: String| {
            errors.push(DeclarationError {
                fb: Some(fb.to_owned()),
                port: port.map(str::to_owned),
                error,
            })
        };
        if self.fbs.len() > MAX_FBS {
            return Err(vec![DeclarationError {
                fb: None,
                port: None,
                error: format!("{} FBs declared; at most {MAX_FBS}", self.fbs.len()),
            }]);
        }
        let mut fbs = BTreeMap::new();
        for (name, fb) in self.fbs {
            if !is_identifier(&name) {
                err(
                    &name,
                    None,
                    "FB name is not an IEC 61131-3 identifier".into(),
                );
                continue;
            }
            let ports =
                fb.events_out.len() + fb.events_in.len() + fb.data_out.len() + fb.data_in.len();
            if ports > MAX_PORTS {
                err(
                    &name,
                    None,
                    format!("{ports} ports declared; at most {MAX_PORTS}"),
                );
                continue;
            }
            let typed = |ports: BTreeMap<String, String>,
                         err: &mut dyn FnMut(&str, Option<&str>, String)| {
                let mut out = BTreeMap::new();
                for (port, ty) in ports {
                    match ty.parse::<DataType>() {
                        Ok(t) => {
                            out.insert(port, t);
                        }
                        Err(e) => err(&name, Some(&port), e.to_string()),
                    }
                }
                out
            };
            let data_out = typed(fb.data_out, &mut err);
            let data_in = typed(fb.data_in, &mut err);

            // Every port name is a topic level of this FB, so names are unique across kinds.
            let mut seen = std::collections::BTreeSet::new();
            let names = fb
                .events_out
                .keys()
                .chain(fb.events_in.keys())
                .chain(data_out.keys())
                .chain(data_in.keys());
            for port in names {
                if !is_identifier(port) {
                    err(
                        &name,
                        Some(port),
                        "port name is not an IEC 61131-3 identifier".into(),
                    );
                } else if !seen.insert(port.as_str()) {
                    err(
                        &name,
                        Some(port),
                        "declared twice (port names are unique within an FB)".into(),
                    );
                }
            }
            let check_with =
                |events: &BTreeMap<String, Event>,
                 data: &BTreeMap<String, DataType>,
                 dir: &str,
                 err: &mut dyn FnMut(&str, Option<&str>, String)| {
                    for (event, e) in events {
                        let mut listed = std::collections::BTreeSet::new();
                        for w in &e.with {
                            if !data.contains_key(w) {
                                err(
                                    &name,
                                    Some(event),
                                    format!("WITH {w}: no data {dir} of that name in this FB"),
                                );
                            } else if !listed.insert(w) {
                                err(&name, Some(event), format!("WITH {w}: listed twice"));
                            }
                        }
                    }
                };
            check_with(&fb.events_out, &data_out, "output", &mut err);
            check_with(&fb.events_in, &data_in, "input", &mut err);
            fbs.insert(
                name,
                FbInterface {
                    fb_type: fb.fb_type,
                    events_out: fb.events_out,
                    events_in: fb.events_in,
                    data_out,
                    data_in,
                },
            );
        }
        Ok((Interface { fbs }, errors))
    }
}

/// An output port a device may publish on, resolved from its interface.
#[derive(Debug, Clone, PartialEq)]
pub enum OutputPort<'a> {
    /// An event output and the (name, type) of each WITH data port, in WITH order.
    Event(Vec<(&'a str, DataType)>),
    /// A data output and its type.
    Data(DataType),
}

impl OutputPort<'_> {
    /// The types of the values one message on this port carries, in order: one for a
    /// data port, the WITH types for an event. A message fits another port with the same
    /// types (what a PUBLISH_1 sends, a SUBSCRIBE_1 reads, whichever kind each is).
    pub fn value_types(&self) -> Vec<DataType> {
        match self {
            OutputPort::Data(t) => vec![*t],
            OutputPort::Event(with) => with.iter().map(|(_, t)| *t).collect(),
        }
    }

    /// Every value on this port has a single JSON form (see
    /// [`ElementaryType::has_one_json_form`](crate::types::ElementaryType::has_one_json_form)).
    pub fn has_one_json_form(&self) -> bool {
        match self {
            OutputPort::Data(t) => t.has_one_json_form(),
            OutputPort::Event(with) => with.iter().all(|(_, t)| t.has_one_json_form()),
        }
    }

    /// Whether `payload`, valid JSON accepted on this port and free of whitespace, is
    /// canonical already, so it can be routed as it came: every value has one JSON form,
    /// but for BOOLs, which must be written `true`/`false`, not `1`/`0` (which BOOL reads
    /// too). A BOOL data port's payload (or a BOOL array's) has no digit; an event's BOOL
    /// values are found by their keys in one pass (`bools_written_as_literals`). Until
    /// 2026-11-28 every event carrying a BOOL was re-encoded, and the conveyor's typed
    /// burst lost a quarter of its throughput (`compare fb`, docs/performance.md).
    pub fn json_is_canonical(&self, payload: &[u8]) -> bool {
        match self {
            OutputPort::Data(t) if t.element() == ElementaryType::Bool => {
                !payload.iter().any(u8::is_ascii_digit)
            }
            OutputPort::Data(t) => t.has_one_json_form(),
            OutputPort::Event(with) => {
                let bools = with
                    .iter()
                    .filter(|(_, t)| t.element() == ElementaryType::Bool);
                match bools.clone().next() {
                    None => self.has_one_json_form(),
                    Some(_) => {
                        with.iter().all(|(_, t)| {
                            t.element() == ElementaryType::Bool || t.has_one_json_form()
                        }) && bools_written_as_literals(payload, |key| {
                            bools.clone().any(|(name, _)| name.as_bytes() == key)
                        })
                    }
                }
            }
        }
    }
}

/// Whether, in `payload` (an event's JSON, valid and without whitespace), no value of a
/// key `is_bool` names is written with a digit (`1`, `[0,true]`): one pass, no
/// allocation. A quote inside a string is escaped, so the strings are found exactly; only
/// an object key is followed by `:`. A key written with an escape cannot be told apart:
/// the payload is then taken as not canonical (re-encoded), never the other way.
fn bools_written_as_literals(payload: &[u8], is_bool: impl Fn(&[u8]) -> bool) -> bool {
    let mut i = 0;
    let mut last: Option<(usize, usize)> = None;
    while i < payload.len() {
        match payload[i] {
            b'"' => {
                let start = i + 1;
                i += 1;
                while i < payload.len() && payload[i] != b'"' {
                    i += if payload[i] == b'\\' { 2 } else { 1 };
                }
                last = Some((start, i.min(payload.len())));
            }
            b':' => {
                if let Some((start, end)) = last.take() {
                    let key = &payload[start..end];
                    if key.contains(&b'\\') {
                        return false;
                    }
                    if is_bool(key) {
                        let value = &payload[i + 1..];
                        let len = match value.first() {
                            Some(b'[') => value.iter().position(|b| *b == b']'),
                            _ => value.iter().position(|b| matches!(b, b',' | b'}')),
                        }
                        .unwrap_or(value.len());
                        if value[..len].iter().any(|b| b.is_ascii_digit()) {
                            return false;
                        }
                    }
                }
            }
            _ => {}
        }
        i += 1;
    }
    true
}

impl Interface {
    /// The output port `fb.port`, if the interface declares one.
    pub fn output(&self, fb: &str, port: &str) -> Option<OutputPort<'_>> {
        let fb = self.fbs.get(fb)?;
        if let Some(ty) = fb.data_out.get(port) {
            return Some(OutputPort::Data(*ty));
        }
        let event = fb.events_out.get(port)?;
        Some(OutputPort::Event(
            event
                .with
                .iter()
                .filter_map(|w| fb.data_out.get(w).map(|t| (w.as_str(), *t)))
                .collect(),
        ))
    }

    /// The input port `fb.port`, if the interface declares one, resolved like an output:
    /// what the device reads there has this shape.
    pub fn input(&self, fb: &str, port: &str) -> Option<OutputPort<'_>> {
        let fb = self.fbs.get(fb)?;
        if let Some(ty) = fb.data_in.get(port) {
            return Some(OutputPort::Data(*ty));
        }
        let event = fb.events_in.get(port)?;
        Some(OutputPort::Event(
            event
                .with
                .iter()
                .filter_map(|w| fb.data_in.get(w).map(|t| (w.as_str(), *t)))
                .collect(),
        ))
    }

    /// Every output port as (fb, port), for registries and bridges.
    pub fn outputs(&self) -> impl Iterator<Item = (&str, &str)> {
        self.fbs.iter().flat_map(|(fb, i)| {
            i.events_out
                .keys()
                .chain(i.data_out.keys())
                .map(move |p| (fb.as_str(), p.as_str()))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decl(json: &str) -> Declaration {
        Declaration::from_json(json.as_bytes()).unwrap()
    }

    #[test]
    fn a_bool_port_is_canonical_only_as_true_and_false() {
        use crate::types::ElementaryType as T;
        let bool_port = OutputPort::Data(DataType::Elementary(T::Bool));
        assert!(bool_port.json_is_canonical(b"true"));
        assert!(!bool_port.json_is_canonical(b"1"));
        let flags = OutputPort::Data(DataType::Array(T::Bool, 2));
        assert!(flags.json_is_canonical(b"[true,false]"));
        assert!(!flags.json_is_canonical(b"[1,false]"));
        let int_port = OutputPort::Data(DataType::Elementary(T::Int));
        assert!(int_port.json_is_canonical(b"1"));
        let event = OutputPort::Event(vec![
            ("ON", DataType::Elementary(T::Bool)),
            ("N", DataType::Elementary(T::Int)),
            ("FLAGS", DataType::Array(T::Bool, 2)),
        ]);
        assert!(
            event.json_is_canonical(br#"{"seq":1,"data":{"ON":true,"N":5,"FLAGS":[false,true]}}"#)
        );
        assert!(
            !event.json_is_canonical(br#"{"seq":1,"data":{"ON":1,"N":5,"FLAGS":[false,true]}}"#)
        );
        assert!(!event.json_is_canonical(br#"{"seq":1,"data":{"N":5,"ON":true,"FLAGS":[0,true]}}"#));
        // A key written with an escape: re-encoded.
        assert!(!event.json_is_canonical(br#"{"data":{"\u004fN":true,"N":5,"FLAGS":[true,true]}}"#));
        // The name inside a string value is not the key.
        let text = OutputPort::Event(vec![
            ("S", DataType::Elementary(T::String)),
            ("ON", DataType::Elementary(T::Bool)),
        ]);
        assert!(text.json_is_canonical(br#"{"data":{"S":"\"ON\":1","ON":false}}"#));
    }

    #[test]
    fn a_name_given_twice_is_refused_not_merged() {
        for json in [
            r#"{"fbs":{"A":{"data_out":{"X":"INT"}},"A":{"data_out":{"Y":"INT"}}}}"#,
            r#"{"fbs":{"A":{"data_out":{"X":"INT","X":"BOOL"}}}}"#,
            r#"{"fbs":{"A":{"events_out":{"E":{"with":[]}},"events_out":{}}}}"#,
        ] {
            let e = Declaration::from_json(json.as_bytes()).unwrap_err();
            let twice = e.error.contains("appears twice") || e.error.contains("duplicate field");
            assert!(twice, "{json}: {e}");
        }
        // The same name in different objects is fine.
        assert!(Declaration::from_json(
            br#"{"fbs":{"A":{"data_out":{"X":"INT"}},"B":{"data_out":{"X":"INT"}}}}"#
        )
        .is_ok());
        assert_eq!(
            duplicate_key(b"[{\"a\":1},{\"a\":2,\"a\":3}]").as_deref(),
            Some("a")
        );
    }

    #[test]
    fn a_good_declaration_resolves_its_outputs() {
        let i = decl(
            r#"{"fbs":{"CONV":{"type":"CONVEYOR",
                "events_out":{"MOVED":{"with":["POSITION","SENSOR_IN"]}},
                "events_in":{"START":{"with":["SPEED"]}},
                "data_out":{"POSITION":"INT","SENSOR_IN":"BOOL"},
                "data_in":{"SPEED":"REAL"}}}}"#,
        )
        .validate()
        .unwrap();
        assert_eq!(
            i.output("CONV", "MOVED"),
            Some(OutputPort::Event(vec![
                ("POSITION", "INT".parse().unwrap()),
                ("SENSOR_IN", "BOOL".parse().unwrap())
            ]))
        );
        assert_eq!(
            i.output("CONV", "POSITION"),
            Some(OutputPort::Data("INT".parse().unwrap()))
        );
        assert_eq!(i.output("CONV", "START"), None, "inputs are not published");
        assert_eq!(i.output("NOPE", "MOVED"), None);
        assert_eq!(i.outputs().count(), 3);
        let json = serde_json::to_string(&i).unwrap();
        assert!(json.contains(r#""POSITION":"INT""#), "{json}");
    }

    #[test]
    fn every_mistake_is_reported_with_its_fb_and_port() {
        let errors = decl(
            r#"{"fbs":{"CONV":{
                "events_out":{"MOVED":{"with":["POSITION","GHOST"]}},
                "data_out":{"POSITION":"FLOAT","MOVED":"INT","bad/name":"INT"}},
               "9x":{}}}"#,
        )
        .validate()
        .unwrap_err();
        let text: Vec<String> = errors.iter().map(|e| e.to_string()).collect();
        assert!(
            text.iter()
                .any(|t| t.contains("FB 9x") && t.contains("identifier")),
            "{text:?}"
        );
        assert!(
            text.iter()
                .any(|t| t.contains("port POSITION") && t.contains("unknown type 'FLOAT'")),
            "{text:?}"
        );
        assert!(
            text.iter()
                .any(|t| t.contains("port MOVED") && t.contains("declared twice")),
            "{text:?}"
        );
        assert!(
            text.iter()
                .any(|t| t.contains("port MOVED") && t.contains("WITH GHOST")),
            "{text:?}"
        );
        assert!(text.iter().any(|t| t.contains("port bad/name")), "{text:?}");
    }

    #[test]
    fn unknown_fields_and_bad_json_are_refused() {
        assert!(Declaration::from_json(br#"{"fbs":{},"extra":1}"#).is_err());
        assert!(Declaration::from_json(b"{").is_err());
    }
}
