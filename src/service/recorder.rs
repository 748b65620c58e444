//! Recording a drive's fresh samples to rotated CSV files on a thread of its own, so that file I/O never delays
//! the poll loop. Rows are flushed at least every 500 ms; [`Recorder::finish`] drains, closes and syncs the file.

use std::path::Path;
use std::sync::mpsc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::recording::RotatingWriter;

use super::state::{COLUMNS, Point};

/// How often buffered rows reach the file.
const FLUSH_EVERY: Duration = Duration::from_millis(500);
/// How often the writer thread takes the rows sent since its last turn.
const DRAIN_EVERY: Duration = Duration::from_millis(100);

/// The sending side; rows go to the writer thread.
pub struct Recorder {
    tx: Option<mpsc::Sender<Point>>,
    thread: Option<JoinHandle<()>>,
}

impl Recorder {
    /// Starts writing `<dir>/<drive>-<unix ms>.csv` files, rotated after `rotate_after` or `max_bytes`.
    pub fn start(dir: &Path, drive: &str, rotate_after: Duration, max_bytes: u64) -> std::io::Result<Recorder> {
        std::fs::create_dir_all(dir)?;
        let mut writer = RotatingWriter::new(dir, drive, &COLUMNS, rotate_after, max_bytes);
        let (tx, rx) = mpsc::channel::<Point>();
        let name = drive.to_string();
        let thread = std::thread::Builder::new().name(format!("rec-{drive}")).spawn(move || {
            let mut failed = false;
            let mut report = |e: std::io::Error| {
                if !failed {
                    tracing::error!(drive = %name, error = %e, "recording failed; rows are being lost");
                    failed = true;
                }
            };
            // the thread drains the channel on its own clock rather than blocking in `recv`: a blocked receiver
            // would be woken by every row, a context switch per poll per drive (a tenth of a 50-drive service's CPU)
            let mut flushed = Instant::now();
            loop {
                std::thread::sleep(DRAIN_EVERY);
                let mut open = true;
                loop {
                    match rx.try_recv() {
                        Ok(p) => {
                            if let Err(e) = writer.write_row(Instant::now(), p.values()) {
                                report(e);
                            }
                        }
                        Err(mpsc::TryRecvError::Empty) => break,
                        Err(mpsc::TryRecvError::Disconnected) => {
                            open = false;
                            break;
                        }
                    }
                }
                if flushed.elapsed() >= FLUSH_EVERY {
                    if let Err(e) = writer.flush() {
                        report(e);
                    }
                    flushed = Instant::now();
                }
                if !open {
                    break;
                }
            }
            if let Err(e) = writer.close() {
                report(e);
            }
        })?;
        Ok(Recorder { tx: Some(tx), thread: Some(thread) })
    }

    pub fn record(&self, p: Point) {
        if let Some(tx) = &self.tx {
            let _ = tx.send(p);
        }
    }

    /// Writes everything sent so far, closes and syncs the file. Blocks until done.
    pub fn finish(mut self) {
        self.tx.take();
        if let Some(t) = self.thread.take()
            && t.join().is_err()
        {
            tracing::error!("the recording thread panicked");
        }
    }
}
