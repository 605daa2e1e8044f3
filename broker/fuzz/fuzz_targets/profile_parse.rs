//! The device-profile reader (`broker::profiles::parse`: TOML, then
//! `ProfileFile::validate`), a set of two profiles indexed together
//! (`ProfileSet::new`), and what the packet path then asks of it: identification,
//! own-topic lookup, and DINASORE string numbers read back for every output port.
//!
//! Input: one profile's text, then optionally a NUL byte and a second profile's text.
//!
//! Checks: nothing panics, whatever the files hold (they are files on disk: hostile
//! until proven otherwise); a profile that parses names a valid device id; every output
//! topic it maps is found again by the index with that profile as its owner.
#![no_main]

use broker::profiles::{parse, ProfileSet};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let (first, second) = match data.iter().position(|b| *b == 0) {
        Some(at) => (&data[..at], Some(&data[at + 1..])),
        None => (data, None),
    };
    let Ok(text) = std::str::from_utf8(first) else {
        return;
    };
    let Ok(profile) = parse(text) else {
        return;
    };
    assert!(fb_bridge::topic::is_device_id(&profile.device));
    for out in &profile.outputs {
        let port = profile
            .interface
            .output(&out.fb, &out.port)
            .expect("a mapped output is a port of the interface");
        let _ = fb_bridge::profile::unstring_numbers(first, &out.port, &port);
    }
    let mut profiles = vec![("a.toml".to_owned(), profile.clone())];
    if let Some(other) = second
        .and_then(|b| std::str::from_utf8(b).ok())
        .and_then(|t| parse(t).ok())
    {
        profiles.push(("b.toml".to_owned(), other));
    }
    let Ok(set) = ProfileSet::new(profiles) else {
        return;
    };
    for out in &profile.outputs {
        let (owner, _) = set.output(&out.topic).expect("indexed");
        assert_eq!(owner.device, profile.device);
    }
    let _ = set.identify(&profile.device, None);
    let _ = set.identify(&profile.device, Some(&profile.device));
});
