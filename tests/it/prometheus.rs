//! Prometheus by the book: `/metrics` of a service polling the simulator, in both formats, through their checkers
//! (`promtool check metrics` for the text format, the OpenMetrics reference parser of Debian's
//! python3-prometheus-client for OpenMetrics); the shipped rules, scrape config and Grafana dashboard checked by
//! promtool and serde_json, and every metric they name found in a real scrape.

use std::collections::BTreeSet;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::Duration;

use crate::support::{self, Stack, wait_for};

/// The Accept header Prometheus 2 sends.
const PROMETHEUS_ACCEPT: &str = "application/openmetrics-text;version=1.0.0,application/openmetrics-text;\
                                 version=0.0.1;q=0.75,text/plain;version=0.0.4;q=0.5,*/*;q=0.1";

fn tool(name: &str, package: &str) -> PathBuf {
    for dir in ["/usr/bin", "/usr/local/bin", "/bin"] {
        let p = Path::new(dir).join(name);
        if p.exists() {
            return p;
        }
    }
    panic!("no {name} found: install Debian's `{package}` (apt-get install -y {package}); tests/run.sh does this");
}

/// Runs `program args` with `stdin` piped in; bounded by the tools themselves (they read stdin or small files).
fn run(program: &Path, args: &[&str], stdin: &str) -> Output {
    let mut child = Command::new(program)
        .args(args)
        .current_dir(support::root())
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("starting {}: {e}", program.display()));
    let mut input = child.stdin.take().expect("stdin");
    input.write_all(stdin.as_bytes()).expect("write stdin");
    drop(input);
    child.wait_with_output().expect("tool output")
}

fn promtool(args: &[&str], stdin: &str) -> Output {
    run(&tool("promtool", "prometheus"), args, stdin)
}

fn report(o: &Output) -> String {
    format!(
        "status {}\nstdout:\n{}\nstderr:\n{}",
        o.status,
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// A leaky plant, checked every second over 5-s windows with a leak limit, written to at a fixed 10 Hz: every
/// family the service has shows up in its scrape (the condition parameters once a check has named the leak).
async fn full_stack() -> Stack {
    let mut text = hydrolens::plant::model::REFERENCE_TOML.to_string();
    text.push_str("\n[effects.internal_leakage]\nl_min_per_bar = 0.08\n");
    let model = hydrolens::plant::PlantModel::parse(&text, "leaky.toml").expect("valid");
    let stack = Stack::start_on(
        model,
        5,
        "[drives.control]\nmode = \"manual\"\nfixed_hz = 10.0\n\n[drives.condition]\nenabled = true\nwindow_s = 5\n\
         every_s = 1\n\n[drives.condition.limits]\ninternal_leakage = { l_min_per_bar = 0.02 }\n",
    )
    .await;
    // the leak named, and enough checks for its trend (past the limit: a time to limit of 0)
    let found = wait_for(Duration::from_secs(25), || async {
        let m = stack.metrics().await;
        m.contains("hydrolens_condition_parameter{") && m.contains("hydrolens_condition_time_to_limit_seconds{")
    })
    .await;
    assert!(found.is_some(), "no condition check named the leak in 20 s:\n{}", stack.metrics().await);
    stack
}

async fn scrape(stack: &Stack, accept: Option<&str>) -> (String, String) {
    let mut req = reqwest::Client::new().get(format!("{}/metrics", stack.url));
    if let Some(a) = accept {
        req = req.header(reqwest::header::ACCEPT, a);
    }
    let resp = req.send().await.expect("GET /metrics");
    assert_eq!(resp.status(), 200);
    let ct = resp.headers()[reqwest::header::CONTENT_TYPE].to_str().expect("ascii").to_string();
    (ct, resp.text().await.expect("body"))
}

/// The names of the sample lines of an exposition (`name{labels} value` or `name value`).
fn sample_names(text: &str) -> BTreeSet<String> {
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
        .map(|l| l.split(['{', ' ']).next().unwrap_or("").to_string())
        .collect()
}

/// The series of an exposition: each sample line without its value.
fn series(text: &str) -> BTreeSet<String> {
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
        .map(|l| l.rsplit_once(' ').map_or(l, |(s, _)| s).to_string())
        .collect()
}

/// Every `hydrolens_…` metric name in a text (rule expressions, dashboard queries).
fn metric_names_in(text: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut rest = text;
    while let Some(i) = rest.find("hydrolens_") {
        let tail = &rest[i..];
        let end = tail.find(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).unwrap_or(tail.len());
        // a word that merely ends in "hydrolens_" (none today) is not a metric
        if i == 0 || !rest[..i].ends_with(|c: char| c.is_ascii_alphanumeric() || c == '_') {
            out.insert(tail[..end].to_string());
        }
        rest = &tail[end..];
    }
    out
}

/// Every string in a JSON value.
fn strings(v: &serde_json::Value, out: &mut Vec<String>) {
    match v {
        serde_json::Value::String(s) => out.push(s.clone()),
        serde_json::Value::Array(a) => a.iter().for_each(|x| strings(x, out)),
        serde_json::Value::Object(o) => o.values().for_each(|x| strings(x, out)),
        _ => {}
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn both_formats_pass_their_checkers_and_carry_the_same_series() {
    let run_ = async {
        let stack = full_stack().await;
        let (ct, text) = scrape(&stack, None).await;
        assert_eq!(ct, "text/plain; version=0.0.4; charset=utf-8");
        let (ct_om, om) = scrape(&stack, Some(PROMETHEUS_ACCEPT)).await;
        assert_eq!(ct_om, "application/openmetrics-text; version=1.0.0; charset=utf-8");
        stack.stop().await;

        // the text format: promtool parses it and its linter (names, units, HELP, counters' _total) finds nothing
        let out = promtool(&["check", "metrics"], &text);
        assert!(out.status.success() && out.stdout.is_empty() && out.stderr.is_empty(), "{}\n{text}", report(&out));
        assert!(!text.contains("# EOF") && !text.contains("# UNIT"), "{text}");
        for name in ["hydrolens_omega_radians_per_second", "hydrolens_inlet_pressure_pascals", "hydrolens_polls_total"]
        {
            assert!(text.contains(&format!("# TYPE {name} ")), "no TYPE line for {name}:\n{text}");
        }

        // OpenMetrics: ends with # EOF, and the reference parser takes it whole (it refuses a missing EOF, a UNIT
        // that is not the name's suffix, a counter sample without _total, unsorted buckets, …)
        assert!(om.ends_with("\n# EOF\n"), "{om}");
        assert!(om.contains("# UNIT hydrolens_load_hat_newton_meters newton_meters\n"), "{om}");
        let parser = "import sys\nfrom prometheus_client.openmetrics.parser import text_string_to_metric_families as p\n\
                      print(len(list(p(sys.stdin.read()))))\n";
        let out = run(&tool("python3", "python3-prometheus-client"), &["-c", parser], &om);
        if String::from_utf8_lossy(&out.stderr).contains("No module named") {
            panic!("no OpenMetrics parser: install Debian's `python3-prometheus-client`; tests/run.sh does this");
        }
        assert!(out.status.success(), "the OpenMetrics parser refuses the exposition: {}\n{om}", report(&out));
        let families: usize = String::from_utf8_lossy(&out.stdout).trim().parse().expect("a count");
        assert_eq!(families, om.matches("# TYPE ").count(), "{}", report(&out));
        // the same series in both (the values moved between the two scrapes)
        assert_eq!(series(&text), series(&om));
    };
    tokio::time::timeout(Duration::from_secs(40), run_).await.expect("bounded");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shipped_rules_config_and_dashboard_check_and_name_only_exported_metrics() {
    // promtool on the files as shipped (the config's rule_files is relative to it: alerts.yml beside it)
    for args in [
        &["check", "rules", "docker/prometheus/alerts.yml"][..],
        &["check", "config", "docker/prometheus/prometheus.yml"],
        &["test", "rules", "docker/prometheus/alerts.test.yml"],
    ] {
        let out = promtool(args, "");
        assert!(out.status.success(), "promtool {args:?}: {}", report(&out));
    }
    let rules = std::fs::read_to_string(support::root().join("docker/prometheus/alerts.yml")).expect("alerts.yml");
    for alert in [
        "HydrolensDriveStale",
        "HydrolensLinkDown",
        "HydrolensModbusErrorsRising",
        "HydrolensRecorderFailing",
        "HydrolensConditionAlarm",
        "HydrolensConditionLimitNear",
        "HydrolensAnotherMaster",
    ] {
        assert!(rules.contains(&format!("alert: {alert}\n")), "alerts.yml lacks {alert}");
    }
    let path = support::root().join("docker/grafana/dashboards/hydrolens.json");
    let dashboard: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).expect("dashboard")).expect("dashboard JSON");
    let mut texts = Vec::new();
    strings(&dashboard, &mut texts);
    let panels = dashboard["panels"].as_array().expect("panels");
    assert!(panels.len() >= 10);
    for p in panels {
        assert_eq!(p["datasource"]["uid"], "prometheus", "panel {}", p["title"]);
        assert!(p["targets"].as_array().is_some_and(|t| t.iter().all(|t| t["expr"].is_string())), "{}", p["title"]);
    }
    for f in [
        "docker/grafana/provisioning/datasources/prometheus.yml",
        "docker/grafana/provisioning/dashboards/hydrolens.yml",
    ] {
        assert!(support::root().join(f).is_file(), "{f}");
    }

    // compose mounts the files from where they are (no YAML parser in the tree: the `- ./src:dst` lines)
    let compose = std::fs::read_to_string(support::root().join("docker/compose.yml")).expect("compose.yml");
    let mounts: Vec<&str> =
        compose.lines().filter_map(|l| l.trim().strip_prefix("- ./")).filter_map(|m| m.split(':').next()).collect();
    for want in ["prometheus/prometheus.yml", "prometheus/alerts.yml", "grafana/provisioning", "grafana/dashboards"] {
        assert!(mounts.contains(&want), "compose.yml does not mount ./{want}: {mounts:?}");
    }
    for m in &mounts {
        assert!(support::root().join("docker").join(m).exists(), "compose.yml mounts ./{m}, which does not exist");
    }

    let run_ = async {
        let stack = full_stack().await;
        let (_, text) = scrape(&stack, None).await;
        stack.stop().await;
        let exported = sample_names(&text);
        let in_rules = metric_names_in(&rules);
        let in_dashboard = metric_names_in(&texts.join("\n"));
        assert!(in_rules.len() >= 5 && in_dashboard.len() >= 25, "{in_rules:?} {in_dashboard:?}");
        for (file, names) in [("alerts.yml", &in_rules), ("hydrolens.json", &in_dashboard)] {
            let missing: Vec<&String> = names.difference(&exported).collect();
            assert!(missing.is_empty(), "{file} names metrics the service does not export: {missing:?}\n{text}");
        }
    };
    tokio::time::timeout(Duration::from_secs(40), run_).await.expect("bounded");
}
