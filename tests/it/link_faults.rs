//! Link faults through the byte-level proxy (drop, refuse, garbage, wrong transaction id, wrong byte count, slow
//! replies), each held long enough to trip the drive's watchdog: the service stays up, is not ready while the link is
//! bad, writes nothing from stale data, counts the errors, reconnects within a second of the link returning, and after
//! `POST /reset` regulates again.

use std::time::{Duration, Instant};

use crate::proxy::Fault;
use crate::support::{Stack, TOKEN, metric, wait_for};

const SPEED: &str = "[drives.control]\nmode = \"speed\"\ntarget_omega_rad_s = 30.0\n";

async fn readyz(stack: &Stack) -> u16 {
    reqwest::get(format!("{}/readyz", stack.url)).await.expect("GET readyz").status().as_u16()
}

async fn regulating(stack: &Stack, limit: Duration) -> Option<Duration> {
    wait_for(limit, || async {
        let t = stack.sim.lock().truth();
        !t.tripped && (t.omega_rad_s - 30.0).abs() < 1.5
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_link_fault_is_survived_and_cleared_by_a_reset() {
    let run = async {
        let (stack, proxy) = Stack::start_behind_proxy(5.0, 10, SPEED).await;
        regulating(&stack, Duration::from_secs(10)).await.expect("regulating before any fault");
        let client = reqwest::Client::new();
        for fault in [
            Fault::Drop,
            Fault::Refuse,
            Fault::Garbage,
            Fault::WrongTransactionId,
            Fault::WrongByteCount,
            Fault::Slow(Duration::from_millis(300)),
        ] {
            let errors_before = stack.status().await["link"]["errors"].as_u64().expect("errors");
            proxy.set(fault);
            wait_for(Duration::from_secs(3), || async { readyz(&stack).await == 503 })
                .await
                .unwrap_or_else(|| panic!("{fault:?}: /readyz must say 503"));
            tokio::time::sleep(Duration::from_millis(150)).await; // a write already in flight may land
            let writes = stack.sim.lock().writes;
            // past the drive's 1 s watchdog: it trips, and nothing is written from stale data meanwhile
            tokio::time::sleep(Duration::from_millis(1300)).await;
            assert_eq!(stack.sim.lock().writes, writes, "{fault:?}: a write reached the drive from stale data");
            assert!(stack.sim.lock().truth().tripped, "{fault:?}: the drive's watchdog took over");
            let status = stack.status().await;
            assert!(status["link"]["errors"].as_u64().expect("errors") > errors_before, "{fault:?}: {status}");

            proxy.set(Fault::Pass);
            let back = Instant::now();
            wait_for(Duration::from_secs(3), || async { readyz(&stack).await == 200 })
                .await
                .unwrap_or_else(|| panic!("{fault:?}: ready again"));
            let reconnect = back.elapsed();
            assert!(reconnect < Duration::from_millis(1500), "{fault:?}: reconnected after {reconnect:?}");
            // tripped: the service never re-arms it by itself
            tokio::time::sleep(Duration::from_millis(300)).await;
            assert!(stack.sim.lock().truth().tripped, "{fault:?}: re-armed without a reset");
            let r = client
                .post(format!("{}/api/drives/pump1/reset", stack.url))
                .bearer_auth(TOKEN)
                .send()
                .await
                .expect("POST reset");
            assert!(r.status().is_success(), "{fault:?}: reset {}", r.status());
            let again = regulating(&stack, Duration::from_secs(8)).await;
            assert!(again.is_some(), "{fault:?}: regulating again after the reset");
            eprintln!(
                "{fault:?}: ready {:.0} ms after the link returned; regulating {:.1} s after the reset",
                reconnect.as_secs_f64() * 1e3,
                again.map_or(f64::NAN, |d| d.as_secs_f64())
            );
        }
        let m = stack.metrics().await;
        assert!(metric(&m, "hydrolens_reconnects_total{drive=\"pump1\"}").expect("reconnects") >= 6.0, "{m}");
        stack.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}
