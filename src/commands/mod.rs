//! The subcommands' work, one room per kind: the files' commands (`simulate`, `estimate`, `analyze`: `files`)
//! and the running ones (`sim`, `serve`, `demo`: `running`); here what they share (the runtimes, the shutdown on a
//! signal, the model file). `main.rs` parses the command line and dispatches to them.

use std::path::Path;

use anyhow::Context;
use hydrolens::plant::PlantModel;
use hydrolens::service;
use tokio_util::sync::CancellationToken;

mod files;
mod running;

pub use files::{analyze, estimate, simulate};
pub use running::{DemoPlant, SimTransport, demo, serve, sim};

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the async runtime")
}

/// The runtime of `serve` and `demo`, which carries the HTTP side. Its workers run at a lower priority than the
/// poll threads (each on a thread and runtime of its own, started from the main thread), so that HTTP load cannot
/// delay the loops.
fn http_runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("http")
        .on_thread_start(service::timing::lower_thread_priority)
        .build()
        .context("starting the async runtime")
}

/// A file-size limit (`ulimit -f`) fails a write past it with EFBIG and sends SIGXFSZ, whose default kills the
/// process: handled for the process's lifetime, the limit is an error the recorder reports and survives, as it does
/// a full disk. Called inside the runtime, before any file is written.
fn file_size_limit_is_an_error() {
    #[cfg(target_os = "linux")]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::from_raw(rustix::process::Signal::XFSZ.as_raw())) {
            Ok(mut xfsz) => {
                tokio::spawn(async move { while xfsz.recv().await.is_some() {} });
            }
            Err(e) => tracing::warn!(error = %e, "cannot handle SIGXFSZ: a file-size limit would stop the process"),
        }
    }
}

/// For the files' commands: on Ctrl-C, SIGTERM or SIGHUP the outputs' temporary files are removed and the process
/// exits (128 + the signal, as the default action's shells report), the old outputs left as they were. By default
/// the signal ended the process at once and left a `.NAME.PID.tmp` of up to the whole run's size until the next run
/// into that path.
fn remove_temporaries_on_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let rt = match tokio::runtime::Builder::new_current_thread().enable_all().build() {
            Ok(rt) => rt,
            Err(e) => return tracing::warn!(error = %e, "cannot handle signals: a stopped run leaves its temporaries"),
        };
        // registered here, before any output is created, so that no signal finds the default action in place
        let kinds = [SignalKind::interrupt(), SignalKind::terminate(), SignalKind::hangup()];
        let handlers: Vec<_> = kinds.iter().map(|&k| rt.block_on(async { signal(k).map(|s| (k, s)) })).collect();
        let Ok(mut handlers) = handlers.into_iter().collect::<std::io::Result<Vec<_>>>() else {
            return tracing::warn!("cannot handle signals: a stopped run leaves its temporaries");
        };
        std::thread::spawn(move || {
            let signo = rt.block_on(async {
                let waits = handlers.iter_mut().map(|(k, s)| Box::pin(async move { s.recv().await.map(|_| *k) }));
                futures::future::select_all(waits).await.0
            });
            hydrolens::output::remove_temporaries();
            let code = signo.map_or(1, |k| 128 + k.as_raw_value());
            eprintln!("stopped by a signal: the outputs' temporary files removed, the old outputs kept");
            std::process::exit(code);
        });
    }
}

/// A token cancelled on Ctrl-C or SIGTERM.
fn shutdown_on_signal() -> CancellationToken {
    let token = CancellationToken::new();
    let t = token.clone();
    // The handlers are registered here, before the caller announces itself, so that a SIGTERM sent right after the
    // announcement is caught (registered inside the task, it could arrive first and kill the process).
    #[cfg(unix)]
    let handlers = {
        use tokio::signal::unix::{SignalKind, signal};
        // SIGHUP (a closed terminal or session) and SIGQUIT end the process too: cleanly, as SIGTERM does, rather
        // than by their default action, which left the recording unclosed
        [SignalKind::terminate(), SignalKind::interrupt(), SignalKind::hangup(), SignalKind::quit()]
            .map(signal)
            .into_iter()
            .collect::<std::io::Result<Vec<_>>>()
    };
    tokio::spawn(async move {
        #[cfg(unix)]
        match handlers {
            Ok(mut signals) => {
                let any = signals.iter_mut().map(|s| Box::pin(s.recv()));
                let _ = futures::future::select_all(any).await;
            }
            Err(e) => {
                tracing::warn!(error = %e, "cannot listen for SIGTERM");
                let _ = tokio::signal::ctrl_c().await;
            }
        }
        #[cfg(not(unix))]
        let _ = tokio::signal::ctrl_c().await;
        tracing::info!("shutting down");
        t.cancel();
        // whatever holds the shutdown up, the process ends: after a grace period, on a thread of its own
        let _ = std::thread::Builder::new().name("shutdown-deadline".into()).spawn(|| {
            std::thread::sleep(SHUTDOWN_GRACE);
            eprintln!("error: not stopped {} s after the signal: exiting", SHUTDOWN_GRACE.as_secs());
            std::process::exit(1);
        });
    });
    token
}

/// How long a signalled shutdown may take (the loops close their recordings) before the process exits anyway.
const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(15);

/// A model file, its `[estimator]` table checked too whether or not the command estimates: `simulate` and `analyze`
/// ran on a table that `estimate` refused (an unknown key, `lambda = 1.5`), and `analyze --model-out` carried it
/// into a model `estimate` then refused.
fn load_model(path: &Path) -> anyhow::Result<PlantModel> {
    let model = PlantModel::load(path)?;
    hydrolens::estimator::EstimatorSettings::from_model(&model, &path.display().to_string())?;
    Ok(model)
}
