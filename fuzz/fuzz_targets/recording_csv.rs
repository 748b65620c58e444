//! Fuzz: any bytes given as a recording either parse into a well-formed recording or give an error; never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(rec) = hydrolens::recording::parse(data, "fuzz.csv") {
        let t = rec.t_s();
        assert!(!t.is_empty());
        assert!(t.iter().all(|v| v.is_finite()));
        assert!(t.windows(2).all(|w| w[0] < w[1]));
        for name in rec.names() {
            assert_eq!(rec.column(name).map(<[f64]>::len), Some(rec.len()));
        }
    }
});
