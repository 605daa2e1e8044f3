//! The 4diac boot-file importers (`fb_bridge::profile::fboot::import`, FORTE's, and
//! `import_dinasore`, a DINASORE's `data_model.fboot`): what `fbbus profile import` reads,
//! a file from outside.
//!
//! Input: the file's bytes, read as `fbbus profile import` reads them (lossy UTF-8).
//!
//! Checks: nothing panics; every derived profile has a usable device id, and one that
//! validates maps each of its output topics once.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let forte = fb_bridge::profile::fboot::import(&text);
    let dinasore = fb_bridge::profile::fboot::import_dinasore(&text, "dinasore");
    for file in forte.profiles.into_iter().chain(dinasore.profiles) {
        assert!(fb_bridge::topic::is_device_id(&file.device), "{}", file.device);
        if let Ok(profile) = file.validate() {
            let mut topics: Vec<&str> = profile.outputs.iter().map(|o| o.topic.as_str()).collect();
            let all = topics.len();
            topics.sort_unstable();
            topics.dedup();
            assert_eq!(topics.len(), all);
        }
    }
});
