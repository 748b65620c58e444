//! Fuzz: any text as a plant model either parses into a valid model that writes back to itself, or gives an error.
#![no_main]

use hydrolens::plant::PlantModel;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(model) = PlantModel::parse(text, "fuzz.toml") {
        assert!(model.validate().is_ok());
        let again = PlantModel::parse(&model.to_toml(), "again").expect("a valid model's TOML parses");
        assert_eq!(again, model);
    }
});
