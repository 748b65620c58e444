//! The config's tests: what parses, and every error naming its key.

use super::condition_monitoring::validate_condition;
use super::*;
use crate::modbus::line::Parity;

const MINIMAL: &str = r#"
[[drives]]
name = "pump1"
address = "127.0.0.1:5020"
"#;

fn err(text: &str) -> String {
    match parse(text, "t.toml", None) {
        Ok(_) => panic!("accepted: {text}"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn minimal_config_gets_safe_defaults() {
    let s = parse(MINIMAL, "t.toml", None).expect("valid");
    assert_eq!(s.http.bind.to_string(), "127.0.0.1:8080");
    assert_eq!(s.http.token, None, "no token: write routes off");
    let d = &s.drives[0];
    assert_eq!(d.mode, Mode::Monitor);
    assert_eq!(d.poll, Duration::from_millis(10));
    assert_eq!(d.registers, RegisterMap::default());
}

/// A speed target is held to one rule at load and over HTTP: at most what `max_hz` gives with no load (78.1 rad/s at
/// 50 Hz on the reference plant). The config accepted up to 1.5× of it, targets `POST …/target` refused with 422, and
/// printed 1e308 as a 309-digit number.
#[test]
fn a_speed_target_beyond_max_hz_is_refused_as_http_refuses_it() {
    let speed = |target: &str| {
        format!("{MINIMAL}[drives.control]\nmode = \"speed\"\nmax_hz = 50.0\ntarget_omega_rad_s = {target}\n")
    };
    let s = parse(&speed("78.0"), "t.toml", None).expect("within max_hz");
    assert!((s.drives[0].max_target_omega_rad_s() - 78.1).abs() < 0.1, "{}", s.drives[0].max_target_omega_rad_s());
    for target in ["79.0", "100.0", "1e308"] {
        let e = err(&speed(target));
        assert!(
            e.contains("drives[0].control.target_omega_rad_s") && e.contains("0 ..= 78.1 (max_hz with no load)"),
            "{e}"
        );
        assert!(e.len() < 200, "{e}");
    }
}

#[test]
fn errors_name_the_key() {
    assert!(err("[http]\nbnd = \"x\"\n").contains("bnd"));
    let e = err(&format!("{MINIMAL}[drives.control]\nmin_hz = 30.0\nmax_hz = 20.0\n"));
    assert!(e.contains("drives[0].control.min_hz"), "{e}");
    let e = err(&format!("{MINIMAL}realtime_priority = 0\n"));
    assert!(e.contains("drives[0].realtime_priority") && e.contains("1 ..= 99"), "{e}");
    let e = err(&format!("{MINIMAL}poll_ms = 10\nstale_ms = 19\n"));
    assert!(e.contains("drives[0].stale_ms") && e.contains("≥ 2 · poll_ms (20)"), "{e}");
    assert!(parse(&format!("{MINIMAL}poll_ms = 10\nstale_ms = 20\n"), "t.toml", None).is_ok());
    let e = err(&format!("{MINIMAL}stale_ms = 600001\n"));
    assert!(e.contains("drives[0].stale_ms") && e.contains("600000"), "{e}");
    // unit 0 is broadcast: a writing drive names its own unit (monitor may read through unit 0)
    let e = err(&format!("{MINIMAL}unit_id = 0\n[drives.control]\nmode = \"speed\"\n"));
    assert!(e.contains("drives[0].unit_id") && e.contains("broadcast"), "{e}");
    assert!(parse(&format!("{MINIMAL}unit_id = 0\n"), "t.toml", None).is_ok());
    // a writing drive polled less often than a third of its comm timeout would trip between polls; monitor may
    let e = err(&format!("{MINIMAL}poll_ms = 2000\n[drives.control]\nmode = \"manual\"\n"));
    assert!(e.contains("drives[0].poll_ms") && e.contains("comm timeout (1000 ms)"), "{e}");
    assert!(parse(&format!("{MINIMAL}poll_ms = 2000\n"), "t.toml", None).is_ok());
    let e = err(&format!("{MINIMAL}comm_timeout_ms = 3600001\n"));
    assert!(e.contains("drives[0].comm_timeout_ms") && e.contains("one hour"), "{e}");
    let e = err(&format!("{MINIMAL}poll_ms = \"fast\"\n"));
    assert!(e.contains("poll_ms"), "{e}");
    let e = err(&format!("{MINIMAL}[drives.registers.inlet_pressure]\naddress = 3\n"));
    assert!(e.contains("drives[0].registers.inlet_pressure"), "{e}");
    let e = err(&format!("{MINIMAL}[drives.registers.watchdog]\ntable = \"input\"\n"));
    assert!(e.contains("watchdog.table"), "{e}");
    let e = err(&format!("{MINIMAL}[drives.control]\nmode = \"turbo\"\n"));
    assert!(e.contains("turbo"), "{e}");
    // a negative scale holds negative frequencies: the range said as it is (it said "at most 655.35 Hz")
    let e = err(&format!("{MINIMAL}[drives.registers.frequency_setpoint_hz]\nscale = -0.01\n"));
    assert!(e.contains("control.max_hz") && e.contains("-655.35 ..= 0 Hz"), "{e}");
    // port 0 is "any port" to bind, and no drive listens on it
    let e = err(&MINIMAL.replace(":5020", ":0"));
    assert!(e.contains("drives[0].address") && e.contains("port 1 ..= 65535"), "{e}");
}

#[test]
fn register_overrides_merge_over_the_default() {
    let text = format!(
        "{MINIMAL}[drives.registers.inlet_pressure_bar]\naddress = 10\ntype = \"f32\"\nscale = 1.0\nword_order = \"cdab\"\n"
    );
    let s = parse(&text, "t.toml", None).expect("valid");
    let m = s.drives[0].registers;
    assert_eq!(m.inlet_pressure_bar.address, 10);
    assert_eq!(m.inlet_pressure_bar.kind, ValueType::F32);
    assert_eq!(m.inlet_pressure_bar.word_order, WordOrder::Cdab);
    assert_eq!(m.inlet_pressure_bar.table, Table::Input);
    assert_eq!(m.span(Table::Input), Some((1, 11)));
    assert_eq!(m.drive_power_w, None, "the drive's power is not read unless named");
}

#[test]
fn the_drive_power_register_is_read_once_named() {
    let s = parse(&format!("{MINIMAL}[drives.registers.drive_power_w]\n"), "t.toml", None).expect("valid");
    assert_eq!(s.drives[0].registers.drive_power_w, Some(crate::modbus::map::DRIVE_POWER_W));
    let text = format!("{MINIMAL}[drives.registers.drive_power_w]\naddress = 40\ntype = \"u16\"\nscale = 10.0\n");
    let p = parse(&text, "t.toml", None).expect("valid").drives[0].registers.drive_power_w.expect("read");
    assert_eq!((p.table, p.address, p.kind, p.scale), (Table::Input, 40, ValueType::U16, 10.0));
    let e = err(&format!("{MINIMAL}[drives.registers.drive_power_w]\naddress = 65535\ntype = \"f32\"\n"));
    assert!(e.contains("drive_power_w.address"), "{e}");
    let e = err(&format!("{MINIMAL}[drives.registers.drive_power]\n"));
    assert!(e.contains("drive_power_w"), "the message names the entry: {e}");
}

fn rtu(name: &str, unit: u8, extra: &str) -> String {
    format!(
        "[[drives]]\nname = \"{name}\"\ntransport = \"rtu\"\nserial_port = \"/dev/ttyUSB0\"\nunit_id = {unit}\n{extra}\n"
    )
}

#[test]
fn rtu_keys_are_validated() {
    let s = parse(&rtu("vfd3", 3, "baud_rate = 19200\nparity = \"none\"\nstop_bits = 2\npoll_ms = 50"), "t", None)
        .expect("valid");
    let d = &s.drives[0];
    assert_eq!(d.address, "/dev/ttyUSB0");
    let line = SerialLine { baud_rate: 19200, parity: Parity::None, stop_bits: 2 };
    assert_eq!(d.transport, Transport::Rtu { serial_port: "/dev/ttyUSB0".into(), line });
    let e = err("[[drives]]\nname = \"v\"\ntransport = \"rtu\"\n");
    assert!(e.contains("drives[0].serial_port") && e.contains("required"), "{e}");
    let e = err(&rtu("v", 1, "parity = \"mark\""));
    assert!(e.contains("drives[0].parity") && e.contains("mark"), "{e}");
    let e = err(&rtu("v", 1, "baud_rate = -9600"));
    assert!(e.contains("drives[0].baud_rate") && e.contains("positive"), "{e}");
    let e = err(&rtu("v", 1, "baud_rate = 0"));
    assert!(e.contains("drives[0].baud_rate"), "{e}");
    let e = err(&rtu("v", 1, "stop_bits = 3"));
    assert!(e.contains("drives[0].stop_bits") && e.contains("1 or 2"), "{e}");
    let e = err(&rtu("v", 0, "poll_ms = 100"));
    assert!(e.contains("drives[0].unit_id"), "{e}");
    let e = err(&format!("{MINIMAL}parity = \"even\"\n"));
    assert!(e.contains("drives[0].parity") && e.contains("tcp"), "{e}");
    let e = err("[[drives]]\nname = \"v\"\ntransport = \"rtu-over-tcp\"\n");
    assert!(e.contains("drives[0].address") && e.contains("required"), "{e}");
    let e = err(&format!("{MINIMAL}transport = \"udp\"\n"));
    assert!(e.contains("drives[0].transport") && e.contains("udp"), "{e}");
}

/// One drive under two spellings is one device: two writing loops at `127.0.0.1:P` and `localhost:P` (or
/// `127.1:P`, `[::ffff:127.0.0.1]:P`) are refused as they would be at one spelling; a monitoring one may watch.
#[test]
fn two_writers_on_one_device_are_refused_whatever_its_spelling() {
    let drive = |name: &str, address: &str, mode: &str| {
        format!(
            "[[drives]]\nname = \"{name}\"\naddress = \"{address}\"\n[drives.control]\nmode = \"{mode}\"\n\
             fixed_hz = 10.0\n"
        )
    };
    for other in ["localhost:5020", "127.1:5020", "[::ffff:127.0.0.1]:5020", "127.0.0.1:5020"] {
        let text = format!("{}{}", drive("a", "127.0.0.1:5020", "manual"), drive("b", other, "manual"));
        let e = err(&text);
        assert!(e.contains("drives[1].address") && e.contains("already written"), "{other}: {e}");
        let watch = format!("{}{}", drive("a", "127.0.0.1:5020", "manual"), drive("b", other, "monitor"));
        parse(&watch, "t", None).expect("one may watch");
    }
    let text = format!("{}{}", drive("a", "127.0.0.1:5020", "manual"), drive("b", "127.0.0.1:5021", "manual"));
    parse(&text, "t", None).expect("another port is another device");
}

#[test]
fn a_line_has_one_setting_and_a_capacity() {
    // two monitoring drives at 50 ms on 19200 baud, even parity: 37 % each, 73 % together: fits
    let two = format!("{}{}", rtu("a", 1, "poll_ms = 50"), rtu("b", 2, "poll_ms = 50"));
    let s = parse(&two, "t", None).expect("fits the line");
    assert_eq!(s.drives.len(), 2);
    // a third one is too many, and the error names every drive on the line
    let three = format!("{two}{}", rtu("c", 3, "poll_ms = 50"));
    let e = err(&three);
    assert!(e.contains("drives[2].serial_port") && e.contains("cannot carry"), "{e}");
    for name in ["\"a\"", "\"b\"", "\"c\""] {
        assert!(e.contains(name), "{e}");
    }
    assert!(e.contains("110 %"), "{e}");
    // writing adds the write exchange: one speed drive at 50 ms takes 37 % + 34 %
    let speed = rtu("a", 1, "poll_ms = 50\n[drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 10.0");
    parse(&speed, "t", None).expect("one writing drive fits");
    let e = err(&format!("{speed}{}", rtu("b", 2, "poll_ms = 50")));
    assert!(e.contains("cannot carry"), "{e}");
    // one line, two settings
    let e = err(&format!("{}{}", rtu("a", 1, "poll_ms = 50"), rtu("b", 2, "poll_ms = 50\nbaud_rate = 9600")));
    assert!(e.contains("drives[1].serial_port") && e.contains("one setting") && e.contains("9600"), "{e}");
    // two writing loops on one device of a line
    let speed2 = speed.replace("name = \"a\"", "name = \"b\"").replace("poll_ms = 50", "poll_ms = 300");
    let e = err(&format!("{}{speed2}", speed.replace("poll_ms = 50", "poll_ms = 300")));
    assert!(e.contains("drives[1].serial_port") && e.contains("already written"), "{e}");
    // other ports are other lines
    let other = rtu("c", 3, "poll_ms = 50").replace("ttyUSB0", "ttyUSB1");
    parse(&format!("{two}{other}"), "t", None).expect("a second line");
}

#[test]
fn a_drives_condition_is_carried_and_its_errors_name_the_drives_key() {
    let base = "[[drives]]\nname = \"pump1\"\naddress = \"127.0.0.1:5020\"\n[drives.condition]\n";
    let parse = |extra: &str| parse(&format!("{base}{extra}"), "t.toml", None);
    let s = parse("enabled = true\nevery_s = 60\n").expect("valid");
    assert!(s.drives[0].condition.enabled);
    assert_eq!(s.drives[0].condition.every, Duration::from_secs(60));
    let e = parse("window_s = 0.5\n").expect_err("too short");
    assert!(e.is_bad_input() && e.to_string().contains("drives[0].condition.window_s"), "{e}");
    let e = parse("enable = true\n").expect_err("unknown key");
    assert!(e.is_bad_input() && e.to_string().contains("enable"), "{e}");
    let e = parse("[drives.condition.limits]\ndead_time = { seconds = 1.0 }\n").expect_err("unknown parameter");
    assert!(e.to_string().contains("drives[0].condition.limits.dead_time.seconds"), "{e}");
}

/// `[drives.condition]` on its own.
mod drives_condition {
    use super::*;

    fn raw(text: &str) -> RawCondition {
        toml::from_str(text).expect("parses")
    }

    fn check(text: &str) -> Result<ConditionSettings, KeyError> {
        validate_condition(raw(text), "drives[0].condition", &PlantModel::reference(), |p: &str| PathBuf::from(p))
    }

    #[test]
    fn defaults_are_off_120_s_every_300_s_on_the_estimators_model_with_the_load_unknown() {
        let s = check("").expect("valid");
        assert!(!s.enabled);
        assert_eq!((s.window, s.every), (Duration::from_secs(120), Duration::from_secs(300)));
        assert_eq!(s.model.load, LoadSpec::Recorded);
        assert_eq!(s.model.motor, PlantModel::reference().motor);
        assert!(s.limits.is_empty());
    }

    #[test]
    fn errors_name_the_key() {
        let key = |text: &str| check(text).expect_err(text).key;
        assert_eq!(key("window_s = 1.0"), "drives[0].condition.window_s");
        assert_eq!(key("every_s = -5.0"), "drives[0].condition.every_s");
        assert_eq!(key("model = \"/no/such/plant.toml\""), "drives[0].condition.model");
        assert_eq!(key("[limits]\nleak = { l_min_per_bar = 0.02 }"), "drives[0].condition.limits.leak");
        assert_eq!(
            key("[limits]\ninternal_leakage = { l_per_bar = 0.02 }"),
            "drives[0].condition.limits.internal_leakage.l_per_bar"
        );
        assert_eq!(key("energy_price_per_kwh = -0.1"), "drives[0].condition.energy_price_per_kwh");
        let unknown = toml::from_str::<RawCondition>("enable = true").expect_err("unknown key").to_string();
        assert!(unknown.contains("enable"), "{unknown}");
    }

    #[test]
    fn the_contracts_example_parses() {
        let s = check(
            "enabled = true\nwindow_s = 120\nevery_s = 60\n[limits]\ninternal_leakage = { l_min_per_bar = 0.02 }\n\
             dead_time = { ms = 50.0 }\nentrained_air = { bulk_modulus_bar = 8000.0 }\n",
        )
        .expect("valid");
        assert!(s.enabled);
        assert_eq!(s.every, Duration::from_secs(60));
        assert_eq!(s.limits["entrained_air"]["bulk_modulus_bar"], 8000.0);
    }
}

#[test]
fn entries_sharing_a_word_are_refused_naming_both() {
    // the setpoint on the control word's holding register: each write would run or fault-reset the drive
    let e = err(&format!("{MINIMAL}[drives.registers.frequency_setpoint_hz]\naddress = 1\n"));
    assert!(e.contains("drives[0].registers.control_word.address") && e.contains("frequency_setpoint_hz"), "{e}");
    // a two-word value reaching into the next entry's word
    let e = err(&format!("{MINIMAL}[drives.registers.inlet_pressure_bar]\ntype = \"f32\"\n"));
    assert!(e.contains("outlet_pressure_bar.address") && e.contains("inlet_pressure_bar"), "{e}");
    // the optional power register on a measured one
    let e = err(&format!("{MINIMAL}[drives.registers.drive_power_w]\naddress = 5\n"));
    assert!(e.contains("drive_power_w.address") && e.contains("sample_counter"), "{e}");
    // the same address in the other table is a different register
    let text =
        format!("{MINIMAL}[drives.registers.watchdog]\naddress = 3\n[drives.registers.drive_power_w]\naddress = 10\n");
    parse(&text, "t.toml", None).expect("holding 3 shares a number with input 3, not a word");
}

/// A model whose `[estimator]` table is wrong is named by its path (the message said "model file the model file").
#[test]
fn a_bad_estimator_table_in_a_drives_model_names_the_model_file() {
    let dir = tempfile::tempdir().expect("tmp");
    let model = dir.path().join("badest.toml");
    let reference = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/config/plant.toml")).expect("plant");
    std::fs::write(&model, format!("{reference}\n[estimator]\nlambda = 5.0\n")).expect("write");
    let e = err(&format!("{MINIMAL}[drives.estimator]\nmodel = {:?}\n", model.display().to_string()));
    assert!(e.contains("drives[0].estimator.model") && e.contains("badest.toml") && e.contains("lambda"), "{e}");
    assert!(!e.contains("the model file"), "{e}");
}

/// A reviewer's control word at `scale = 0.5` sent RUN as bit 1 (and setpoints kept climbing), a status word at
/// `scale = 2` read the drive's ready as running, and a watchdog at `scale = 1e-9` failed every encode: bit fields
/// and counters are refused any scale, offset or float, naming the key.
#[test]
fn bit_fields_and_counters_take_no_scale_offset_or_float() {
    for entry in ["status_word", "sample_counter", "control_word", "watchdog"] {
        let e = err(&format!("{MINIMAL}[drives.registers.{entry}]\nscale = 0.5\n"));
        assert!(e.contains(&format!("drives[0].registers.{entry}.scale")) && e.contains("must be 1"), "{e}");
        let e = err(&format!("{MINIMAL}[drives.registers.{entry}]\noffset = 2.0\n"));
        assert!(e.contains(&format!("drives[0].registers.{entry}.offset")) && e.contains("must be 0"), "{e}");
        let e = err(&format!("{MINIMAL}[drives.registers.{entry}]\naddress = 60\ntype = \"f32\"\n"));
        assert!(e.contains(&format!("drives[0].registers.{entry}.type")), "{e}");
    }
    // as the drive gives them, in another type and place: accepted
    let text = format!("{MINIMAL}[drives.registers.watchdog]\naddress = 20\ntype = \"i16\"\nscale = 1.0\n");
    assert!(parse(&text, "t.toml", None).is_ok());
}

/// A token no client can send as `Authorization: Bearer <token>` (a space, a line end, a non-ASCII letter) is refused
/// naming `http.token`: accepted, the write routes could never be used.
#[test]
fn a_token_no_client_can_send_is_refused() {
    for token in [" 0123456789abcdef0123 ", "0123456789abcdef\\n0123", "pässwörd-pässwörd-ü", "tab\\there-0123456789"]
    {
        let e = err(&format!("[http]\ntoken = \"{token}\"\n{MINIMAL}"));
        assert!(e.contains("http.token") && e.contains("visible ASCII"), "{token:?}: {e}");
    }
    let ok = parse(&format!("[http]\ntoken = \"0123456789abcdef-_.~+/=\"\n{MINIMAL}"), "t.toml", None).expect("valid");
    assert_eq!(ok.http.token.as_deref(), Some("0123456789abcdef-_.~+/="));
}

/// A config error never repeats a secret: the broker URL's credentials (the check that keeps them out of the URL
/// echoed them), nor the value on a quoted source line whose key names one (a typo on the `password` or `token` line
/// put it in the journal).
#[test]
fn errors_do_not_repeat_secrets() {
    let url = format!("{MINIMAL}[mqtt]\nurl = \"mqtt://hluser:UrlSecretPw55@127.0.0.1:1883\"\n");
    let e = err(&url);
    assert!(e.contains("mqtt.url") && e.contains("127.0.0.1:1883") && !e.contains("UrlSecretPw55"), "{e}");
    let e = err(&url.replace("mqtt://", "tcp://"));
    assert!(e.contains("mqtt.url") && !e.contains("UrlSecretPw55"), "{e}");
    for line in ["password = \"SuperSecretPw9876", "passwd = \"SuperSecretPw9876\"", "Password = 'SuperSecretPw9876' x"]
    {
        let e = err(&format!("{MINIMAL}[mqtt]\nurl = \"mqtt://127.0.0.1:1883\"\n{line}\n"));
        assert!(e.contains("line 7") && !e.contains("SuperSecretPw9876"), "{line}: {e}");
    }
    let e = err(&format!("[http]\ntoken = \"HttpSecretToken42{MINIMAL}"));
    assert!(!e.contains("HttpSecretToken42"), "{e}");
    // a misspelt key names no secret, but is unknown: its value is not repeated either
    for line in ["pasword = \"SuperSecretPw9876\"", "tokn = \"SuperSecretPw9876\""] {
        let e = err(&format!("{MINIMAL}[mqtt]\nurl = \"mqtt://127.0.0.1:1883\"\n{line}\n"));
        assert!(e.contains("unknown field") && !e.contains("SuperSecretPw9876"), "{line}: {e}");
    }
    // a secret given as a number: serde's message names the value
    let e = err(&format!("{MINIMAL}[mqtt]\nurl = \"mqtt://127.0.0.1:1883\"\npassword = 98765432\n"));
    assert!(e.contains("invalid type") && !e.contains("98765432"), "{e}");
    // other lines are quoted as they are
    let e = err(&format!("{MINIMAL}poll_ms = \"ten\"\n"));
    assert!(e.contains("\"ten\""), "{e}");
}

/// A writing drive's trip latch is kept in `recording.dir` with recording on or off: with it off, the latch had no
/// place, and a service killed while its drive was latched sent RUN when started again (a reviewer's run).
#[test]
fn the_trip_latch_has_its_place_with_recording_off() {
    let off = parse(&format!("[recording]\nenabled = false\ndir = \"/var/lib/hl\"\n{MINIMAL}"), "t.toml", None)
        .expect("valid");
    assert_eq!(off.recording.dir, None, "nothing recorded");
    assert_eq!(off.recording.latch_dir.as_deref(), Some(std::path::Path::new("/var/lib/hl")));
    let none = parse(&format!("[recording]\nenabled = false\ndir = \"\"\n{MINIMAL}"), "t.toml", None).expect("valid");
    assert_eq!(none.recording.latch_dir, None);
}

/// A writing drive's `control.max_hz` above the plant model's own `[drive] max_hz` (the reference plant's 60 Hz here)
/// is refused naming both: 400 Hz was taken in silence (a reviewer's config).
#[test]
fn a_top_frequency_above_the_drives_own_is_refused() {
    let speed = |max_hz: &str| format!("{MINIMAL}[drives.control]\nmode = \"speed\"\nmax_hz = {max_hz}\n");
    let e = err(&speed("400.0"));
    assert!(e.contains("drives[0].control.max_hz") && e.contains("max_hz (60 Hz)"), "{e}");
    parse(&speed("60.0"), "t.toml", None).expect("at the drive's own top");
    parse(&format!("{MINIMAL}[drives.control]\nmax_hz = 400.0\n"), "t.toml", None)
        .expect("monitor mode writes nothing");
}
