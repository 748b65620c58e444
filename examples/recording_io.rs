//! Times reading (`recording::load`) and writing (`recording::write_csv` to a sink) of recording files, for the
//! "how cost grows with recording length" table of docs/performance.md.
//!
//! usage: `cargo run --release --example recording_io -- [--repeats N] FILE.csv...`
//! Prints per file: rows, MB, and the median wall and thread-CPU seconds of N reads and N writes, with rows/s.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use hydrolens::recording;
use rustix::time::{ClockId, clock_gettime};

fn cpu_s() -> f64 {
    let t = clock_gettime(ClockId::ThreadCPUTime);
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 { v[n / 2] } else { (v[n / 2 - 1] + v[n / 2]) / 2.0 }
}

/// Runs `f` `repeats` times; the median (wall s, CPU s).
fn timed(repeats: usize, mut f: impl FnMut() -> Result<(), String>) -> Result<(f64, f64), String> {
    let (mut wall, mut cpu) = (Vec::new(), Vec::new());
    for _ in 0..repeats {
        let (w0, c0) = (Instant::now(), cpu_s());
        f()?;
        cpu.push(cpu_s() - c0);
        wall.push(w0.elapsed().as_secs_f64());
    }
    Ok((median(wall), median(cpu)))
}

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1).peekable();
    let mut repeats = 3usize;
    let mut files = Vec::new();
    while let Some(a) = args.next() {
        if a == "--repeats" {
            match args.next().and_then(|n| n.parse().ok()) {
                Some(n) if n > 0 => repeats = n,
                _ => {
                    eprintln!("--repeats: expected a positive whole number");
                    return ExitCode::from(2);
                }
            }
        } else {
            files.push(PathBuf::from(a));
        }
    }
    if files.is_empty() {
        eprintln!("usage: recording_io [--repeats N] FILE.csv...");
        return ExitCode::from(2);
    }
    println!(
        "| file | rows | MB | read s (wall / CPU) | read rows/s (CPU) | write s (wall / CPU) | write rows/s (CPU) |"
    );
    println!("|---|---|---|---|---|---|---|");
    for path in files {
        let result = (|| -> Result<(), String> {
            let bytes = std::fs::metadata(&path).map_err(|e| e.to_string())?.len();
            let mut rec = None;
            let read = timed(repeats, || {
                rec = Some(recording::load(&path).map_err(|e| e.to_string())?);
                Ok(())
            })?;
            let rec = rec.ok_or("nothing read")?;
            let write = timed(repeats, || recording::write_csv(std::io::sink(), &rec).map_err(|e| e.to_string()))?;
            let rows = rec.len() as f64;
            println!(
                "| {} | {} | {:.1} | {:.3} / {:.3} | {:.2} M | {:.3} / {:.3} | {:.2} M |",
                path.file_name().map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned()),
                rec.len(),
                bytes as f64 / 1e6,
                read.0,
                read.1,
                rows / read.1 / 1e6,
                write.0,
                write.1,
                rows / write.1 / 1e6,
            );
            Ok(())
        })();
        if let Err(e) = result {
            eprintln!("{}: {e}", path.display());
            return ExitCode::from(1);
        }
    }
    ExitCode::SUCCESS
}
