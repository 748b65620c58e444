//! Several drives in one service, each its own connection and unit id; and a sensor that reports a non-finite value.

use std::time::Duration;

use crate::support::{Stack, get_json, metric, start_service, start_sim, stop_service, test_plant, wait_for};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_drives_are_polled_and_regulated_independently() {
    let run = async {
        let (sim_a, addr_a, stop_a, task_a) = start_sim(test_plant(4.0), 0).await;
        let (sim_b, addr_b, stop_b, task_b) = start_sim(test_plant(9.0), 0).await;
        let dir = tempfile::tempdir().expect("tmp");
        let drive = |name: &str, addr, unit: u8, target: f64| {
            format!(
                "[[drives]]\nname = \"{name}\"\naddress = \"{addr}\"\nunit_id = {unit}\npoll_ms = 5\ntimeout_ms = 100\n\
                 [drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = {target:?}\n"
            )
        };
        let text = format!(
            "[http]\nbind = \"127.0.0.1:0\"\ntoken = \"t\"\n[recording]\ndir = {:?}\n{}{}",
            dir.path().display().to_string(),
            drive("pump1", addr_a, 1, 30.0),
            drive("pump2", addr_b, 2, 45.0)
        );
        let svc = start_service(&text).await;
        let url = svc.url.clone();
        let near = |sim: &hydrolens::modbus::simulator::SimHandle, target: f64| {
            (sim.lock().truth().omega_rad_s - target).abs() < 0.05 * target
        };
        wait_for(Duration::from_secs(10), || async { near(&sim_a, 30.0) && near(&sim_b, 45.0) })
            .await
            .expect("both drives at their own targets");
        let status = get_json(format!("{url}/api/status")).await;
        let names: Vec<&str> =
            status["drives"].as_array().expect("drives").iter().filter_map(|d| d["name"].as_str()).collect();
        assert_eq!(names, ["pump1", "pump2"]);
        let m = reqwest::get(format!("{url}/metrics")).await.expect("metrics").text().await.expect("text");
        for d in ["pump1", "pump2"] {
            assert!(metric(&m, &format!("hydrolens_polls_total{{drive=\"{d}\"}}")).expect("polls") > 100.0, "{m}");
        }
        stop_service(svc).await;
        let files: Vec<String> = std::fs::read_dir(dir.path())
            .expect("recordings")
            .filter_map(|e| e.ok()?.file_name().into_string().ok())
            .collect();
        for d in ["pump1", "pump2"] {
            assert!(files.iter().any(|f| f.starts_with(d)), "a recording per drive: {files:?}");
        }
        stop_a.cancel();
        stop_b.cancel();
        let _ = (task_a.await, task_b.await);
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// The inlet pressure read as an f32 spanning registers 0–1: a high word of 0x7FC0 is NaN whatever the low word.
/// Register 1 is then the f32's alone (entries may not share a word), so the outlet pressure is read from the
/// simulator's spare register 6, scaled small and offset to stay a plausible pressure.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_non_finite_sensor_value_is_rejected_and_never_reaches_the_estimator() {
    let run = async {
        let extra = "[drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 30.0\n\
                     [drives.registers.inlet_pressure_bar]\naddress = 0\ntype = \"f32\"\nscale = 1.0\n\
                     [drives.registers.outlet_pressure_bar]\naddress = 6\ntype = \"i16\"\nscale = 0.0001\n\
                     offset = 5.0\n";
        let stack = Stack::start(5.0, 10, extra).await;
        wait_for(Duration::from_secs(15), || async { stack.state.ready() }).await.expect("fresh data");
        stack.sim.lock().faults.inlet_pressure_override_bar = Some(f64::from(0x7FC0u16) * 0.01);
        let rejected = wait_for(Duration::from_secs(15), || async {
            stack.status().await["link"]["rejected_samples"].as_u64().unwrap_or(0) > 10
        })
        .await;
        assert!(rejected.is_some(), "NaN samples rejected and counted: {}", stack.status().await);
        let writes = stack.sim.lock().writes;
        stack.wait_polls(30, "rejected samples").await;
        assert_eq!(stack.sim.lock().writes, writes, "no write while every sample is rejected");
        let s = stack.status().await;
        assert_eq!(s["link"]["stale"], true, "{s}");
        for key in ["omega_hat_rad_s", "load_hat_nm", "inertia_hat_kg_m2", "viscous_hat_nm_s_rad"] {
            assert!(s["estimate"][key].as_f64().is_some_and(f64::is_finite), "{key} stays finite: {s}");
        }
        stack.sim.lock().faults.inlet_pressure_override_bar = None;
        wait_for(Duration::from_secs(15), || async { stack.status().await["link"]["stale"] == false })
            .await
            .expect("fresh again");
        stack.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}
