//! Fuzz: any text as a service config either parses into validated settings or gives an error naming the key.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(settings) = hydrolens::service::config::parse(text, "fuzz.toml", None) {
        for d in &settings.drives {
            assert!(d.limits.min_hz <= d.limits.max_hz);
            assert!(!d.poll.is_zero());
        }
    }
});
