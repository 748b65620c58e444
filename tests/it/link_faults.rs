//! Every fault of the harness, each held long enough to trip the drive's watchdog: through the byte-level proxy (drop,
//! refuse, garbage, wrong transaction id, wrong byte count, slow replies) and in the simulator (stalled replies, no
//! reply, Modbus exceptions, a frozen sample counter, an out-of-range sensor). The service stays up, is not ready while
//! the data are bad, writes nothing from stale data, counts what went wrong in `/api/status` and `/metrics`, is ready
//! again within about a second of the fault clearing, and after `POST /reset` regulates again.

use std::time::{Duration, Instant};

use hydrolens::modbus::simulator::Faults;
use tokio_modbus::ExceptionCode;

use crate::proxy::{Fault, FaultProxy};
use crate::support::{self, Stack, metric, wait_for};

/// One fault of the harness and the `/api/status` link counter it must move.
#[derive(Debug, Clone, Copy)]
enum Injected {
    Link(Fault),
    Sim(Faults, &'static str),
}

impl Injected {
    fn counter(&self) -> &'static str {
        match self {
            Injected::Link(_) => "errors",
            Injected::Sim(_, counter) => counter,
        }
    }

    fn apply(&self, stack: &Stack, proxy: &FaultProxy) {
        match *self {
            Injected::Link(f) => proxy.set(f),
            Injected::Sim(f, _) => stack.sim.lock().faults = f,
        }
    }

    /// How long the link holds back a request sent while the fault is on.
    fn link_delay(&self) -> Duration {
        match *self {
            Injected::Link(Fault::Slow(d)) => d,
            // the simulator applies a write before it delays or withholds the reply
            _ => Duration::ZERO,
        }
    }

    fn clear(&self, stack: &Stack, proxy: &FaultProxy) {
        proxy.set(Fault::Pass);
        stack.sim.lock().faults = Faults::default();
    }
}

const SPEED: &str = crate::support::SPEED_30;

async fn regulating(stack: &Stack, limit: Duration) -> Option<Duration> {
    wait_for(limit, || async {
        let t = stack.sim.lock().truth();
        !t.tripped && (t.omega_rad_s - 30.0).abs() < 1.5
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_fault_is_survived_and_cleared_by_a_reset() {
    let run = async {
        let (stack, proxy) = Stack::start_behind_proxy(5.0, 10, SPEED).await;
        regulating(&stack, Duration::from_secs(10)).await.expect("regulating before any fault");
        let sim = Faults::default();
        for fault in [
            Injected::Link(Fault::Drop),
            Injected::Link(Fault::Refuse),
            Injected::Link(Fault::Garbage),
            Injected::Link(Fault::WrongTransactionId),
            Injected::Link(Fault::WrongByteCount),
            Injected::Link(Fault::Slow(Duration::from_millis(300))),
            Injected::Sim(Faults { reply_delay: Some(Duration::from_millis(400)), ..sim }, "errors"),
            Injected::Sim(Faults { no_reply: true, ..sim }, "errors"),
            Injected::Sim(Faults { exception: Some(ExceptionCode::ServerDeviceFailure), ..sim }, "errors"),
            Injected::Sim(Faults { freeze_counter: true, ..sim }, "polls"),
            Injected::Sim(Faults { inlet_pressure_override_bar: Some(650.0), ..sim }, "rejected_samples"),
        ] {
            let counter = fault.counter();
            let count_before = stack.status().await["link"][counter].as_u64().expect("counter");
            fault.apply(&stack, &proxy);
            wait_for(Duration::from_secs(15), || async { stack.readyz().await == 503 })
                .await
                .unwrap_or_else(|| panic!("{fault:?}: /readyz must say 503"));
            // a write decided from fresh data and already in flight may land; a slow link holds it back by its own
            // delay (the proxy delays every request it forwards), so wait that long too
            stack.wait_polls(2, "a write in flight lands").await;
            if !fault.link_delay().is_zero() {
                tokio::time::sleep(fault.link_delay()).await; // the fault's own delay, as injected
            }
            let writes = stack.sim.lock().writes;
            // the drive's 1 s watchdog trips, and nothing is written from stale data meanwhile (the deadline only
            // bounds the wait: the simulator steps its plant on this loaded process's clock)
            wait_for(Duration::from_secs(15), || async { stack.sim.lock().truth().tripped })
                .await
                .unwrap_or_else(|| panic!("{fault:?}: the drive's watchdog took over"));
            assert_eq!(stack.sim.lock().writes, writes, "{fault:?}: a write reached the drive from stale data");
            let status = stack.status().await;
            assert!(status["link"][counter].as_u64().expect("counter") > count_before, "{fault:?}: {status}");
            assert_eq!(status["link"]["stale"], true, "{fault:?}: {status}");

            fault.clear(&stack, &proxy);
            let back = Instant::now();
            wait_for(Duration::from_secs(15), || async { stack.readyz().await == 200 })
                .await
                .unwrap_or_else(|| panic!("{fault:?}: ready again"));
            let reconnect = back.elapsed();
            // the back-off is capped at 1 s; add a poll and the readiness check's own granularity
            assert!(reconnect < Duration::from_millis(1200), "{fault:?}: ready again after {reconnect:?}");
            // tripped: the service never re-arms it by itself
            stack.wait_polls(30, "ready, not reset").await;
            assert!(stack.sim.lock().truth().tripped, "{fault:?}: re-armed without a reset");
            let r = support::post_reset(&stack.url).await;
            assert_eq!(r, 202, "{fault:?}: reset {r}");
            // the simulated ramp back to the target takes 5–7.5 s; the deadline only bounds the wait
            let again = regulating(&stack, Duration::from_secs(15)).await;
            assert!(again.is_some(), "{fault:?}: regulating again after the reset");
            eprintln!(
                "{fault:?}: ready {:.0} ms after the link returned; regulating {:.1} s after the reset",
                reconnect.as_secs_f64() * 1e3,
                again.map_or(f64::NAN, |d| d.as_secs_f64())
            );
        }
        let m = stack.metrics().await;
        assert!(metric(&m, "hydrolens_reconnects_total{drive=\"pump1\"}").expect("reconnects") >= 6.0, "{m}");
        assert!(metric(&m, "hydrolens_stale_samples_total{drive=\"pump1\"}").expect("stale samples") >= 1.0, "{m}");
        assert!(metric(&m, "hydrolens_rejected_samples_total{drive=\"pump1\"}").expect("rejected") >= 1.0, "{m}");
        stack.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(180), run).await.expect("bounded");
}
