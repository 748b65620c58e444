//! The HTTP API: bad input gets 4xx with a JSON body (tower `oneshot`, no socket), SSE and metrics over a socket.

use std::time::Duration;

use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use futures::StreamExt;
use hydrolens::http::bounded::Bounded;
use hydrolens::http::{AppState, router};
use hydrolens::service;
use tokio_util::sync::CancellationToken;
use tower::ServiceExt;

use crate::support::{self, Stack, TOKEN, wait_for};

/// A service whose drive points at a closed port: the router works, the drive is down.
fn make_app(token: Option<&str>, mode: &str) -> (axum::Router, CancellationToken, tempfile::TempDir) {
    let (state, shutdown, dir) = make_state(token, mode);
    (router(state), shutdown, dir)
}

/// [`make_app`]'s state, before it becomes a router.
fn make_state(token: Option<&str>, mode: &str) -> (AppState, CancellationToken, tempfile::TempDir) {
    let dir = tempfile::tempdir().expect("tmp");
    let text = support::config_text(
        "127.0.0.1:9".parse().expect("addr"),
        dir.path(),
        50,
        &format!("[drives.control]\nmode = \"{mode}\"\n"),
    );
    let settings = service::config::parse(&text, "t", None).expect("valid");
    let shutdown = CancellationToken::new();
    let svc = service::start(&settings, shutdown.clone()).expect("starts");
    let mut http = settings.http.clone();
    http.token = token.map(str::to_string);
    http.max_body_bytes = 1024;
    let metrics = hydrolens::http::HttpMetrics::register(&mut svc.state.registry());
    (AppState::new(svc.state.clone(), &http, metrics, shutdown.clone()), shutdown, dir)
}

/// `/api/history` replies in flight are bounded ([`hydrolens::http::MAX_HISTORY_REPLIES`]): a reply holds its permit
/// until its body is read to the end or dropped, and one beyond gets 503 with `Retry-After`. Built whole and held
/// until read, 120 replies nobody read took the service to 1.3 GB.
#[tokio::test]
async fn history_replies_in_flight_are_bounded_until_read() {
    let (state, stop, _dir) = make_state(None, "monitor");
    let permits = state.history_replies.clone();
    assert_eq!(permits.available(), hydrolens::http::MAX_HISTORY_REPLIES);
    let body = bounded_until_read(router(state), "/api/history?drive=pump1&seconds=5", &permits).await;
    let json: serde_json::Value = serde_json::from_slice(&body).expect("json");
    assert_eq!(json["drive"], "pump1");
    stop.cancel();
}

/// Recordings downloaded at once are bounded ([`hydrolens::http::MAX_DOWNLOADS`]) as history replies are. 512 slow
/// downloads held every connection and took the service from 12 to 310 MB.
#[tokio::test]
async fn downloads_at_once_are_bounded_until_read() {
    let (state, stop, dir) = make_state(None, "monitor");
    std::fs::write(dir.path().join("pump1-1.csv"), "t_s,omega_rad_s\n0,1\n").expect("a recording");
    let permits = state.downloads.clone();
    assert_eq!(permits.available(), hydrolens::http::MAX_DOWNLOADS);
    let body = bounded_until_read(router(state), "/api/recordings/pump1-1.csv", &permits).await;
    assert_eq!(&body[..], b"t_s,omega_rad_s\n0,1\n");
    stop.cancel();
}

/// Asks `uri` from one address as often as its share allows ([`hydrolens::http::bounded::address_share`]) without
/// reading the answers, then from another for the rest of `permits`; beyond, each gets 503 with `Retry-After`, the
/// first address for its share, the next for all taken. A reply read to its end frees its permit, and the others
/// dropped (their clients gone) free theirs. The body read.
async fn bounded_until_read(app: axum::Router, uri: &str, permits: &Bounded) -> axum::body::Bytes {
    let max = permits.available();
    let share = hydrolens::http::bounded::address_share(max);
    let ask = |ip: [u8; 4]| {
        let mut req = get(uri);
        req.extensions_mut().insert(axum::extract::ConnectInfo(std::net::SocketAddr::from((ip, 40000))));
        app.clone().oneshot(req)
    };
    let (a, b) = ([127, 0, 0, 2], [127, 0, 0, 3]);
    let mut unread = Vec::new();
    for k in 0..max {
        let resp = ask(if k < share { a } else { b }).await.expect("infallible");
        assert_eq!(resp.status(), StatusCode::OK);
        unread.push(resp);
        if k + 1 == share {
            let busy = ask(a).await.expect("infallible");
            assert_eq!(busy.status(), StatusCode::SERVICE_UNAVAILABLE, "beyond its address's share");
            let body = axum::body::to_bytes(busy.into_body(), usize::MAX).await.expect("body");
            assert!(String::from_utf8_lossy(&body).contains("share"), "{body:?}");
        }
    }
    assert_eq!(permits.available(), 0);
    let busy = ask(b).await.expect("infallible");
    assert_eq!(busy.status(), StatusCode::SERVICE_UNAVAILABLE);
    assert!(busy.headers().contains_key(header::RETRY_AFTER));
    let read = unread.pop().expect("a reply").into_body();
    let bytes = axum::body::to_bytes(read, usize::MAX).await.expect("body");
    assert_eq!(permits.available(), 1, "a reply read to its end frees its permit");
    drop(unread);
    assert_eq!(permits.available(), max, "a client gone frees its reply's");
    assert_eq!(ask(a).await.expect("infallible").status(), StatusCode::OK);
    bytes
}

/// One client address holds at most [`hydrolens::http::bounded::address_share`] of the event streams; the rest stay for the
/// others, up to `http.max_event_streams` in all. One address held all 64 with streams it did not read, and every
/// other client got 503.
#[tokio::test]
async fn one_address_holds_at_most_its_share_of_the_event_streams() {
    let (state, stop, _dir) = make_state(None, "monitor");
    let (max, share) = (64, hydrolens::http::bounded::address_share(64));
    assert_eq!(share, 48);
    let app = router(state);
    let from = |ip: [u8; 4]| {
        let mut req = get("/api/events");
        req.extensions_mut().insert(axum::extract::ConnectInfo(std::net::SocketAddr::from((ip, 40000))));
        app.clone().oneshot(req)
    };
    let (a, b) = ([127, 0, 0, 2], [127, 0, 0, 3]);
    let mut open_a = Vec::new();
    for _ in 0..share {
        let resp = from(a).await.expect("infallible");
        assert_eq!(resp.status(), StatusCode::OK);
        open_a.push(resp);
    }
    let (status, body) = {
        let resp = from(a).await.expect("infallible");
        let status = resp.status();
        (status, axum::body::to_bytes(resp.into_body(), usize::MAX).await.expect("body"))
    };
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "beyond its share");
    assert!(String::from_utf8_lossy(&body).contains("share"), "{body:?}");
    let mut open_b = Vec::new();
    for _ in share..max {
        let resp = from(b).await.expect("infallible");
        assert_eq!(resp.status(), StatusCode::OK, "another address gets the rest");
        open_b.push(resp);
    }
    assert_eq!(from(b).await.expect("infallible").status(), StatusCode::SERVICE_UNAVAILABLE, "all taken");
    drop(open_a.pop());
    assert_eq!(from(a).await.expect("infallible").status(), StatusCode::OK, "a stream gone frees its place");
    drop((open_a, open_b));
    stop.cancel();
}

async fn call(app: &axum::Router, req: Request<Body>) -> (StatusCode, serde_json::Value) {
    let resp = app.clone().oneshot(req).await.expect("infallible");
    let status = resp.status();
    let bytes = axum::body::to_bytes(resp.into_body(), usize::MAX).await.expect("body");
    let json = serde_json::from_slice(&bytes).unwrap_or(serde_json::Value::Null);
    (status, json)
}

fn post(uri: &str, token: Option<&str>, body: impl Into<Body>) -> Request<Body> {
    let mut b = Request::post(uri).header(header::CONTENT_TYPE, "application/json");
    if let Some(t) = token {
        b = b.header(header::AUTHORIZATION, format!("Bearer {t}"));
    }
    b.body(body.into()).expect("request")
}

fn get(uri: &str) -> Request<Body> {
    Request::get(uri).body(Body::empty()).expect("request")
}

#[tokio::test]
async fn bad_input_gets_4xx_with_a_json_error() {
    let (app, stop, _dir) = make_app(Some(TOKEN), "speed");
    let target = "/api/drives/pump1/target";
    let ok_body = r#"{"target_omega_rad_s": 30.0}"#;
    let cases: Vec<(Request<Body>, StatusCode)> = vec![
        (post(target, None, ok_body), StatusCode::UNAUTHORIZED),
        (post(target, Some("nope"), ok_body), StatusCode::UNAUTHORIZED),
        (post(target, Some(TOKEN), "{not json"), StatusCode::BAD_REQUEST),
        (post(target, Some(TOKEN), r#"{"target_omega_rad_s": "fast"}"#), StatusCode::BAD_REQUEST),
        (post(target, Some(TOKEN), r#"{"target_omega_rad_s": 30, "extra": 1}"#), StatusCode::BAD_REQUEST),
        (post(target, Some(TOKEN), r#"{"target_omega_rad_s": -1}"#), StatusCode::UNPROCESSABLE_ENTITY),
        (post(target, Some(TOKEN), "[40]"), StatusCode::BAD_REQUEST),
        // two targets in one body: the last one was taken
        (post(target, Some(TOKEN), r#"{"target_omega_rad_s":30,"target_omega_rad_s":70}"#), StatusCode::BAD_REQUEST),
        (post(target, Some(TOKEN), vec![b' '; 1 << 20]), StatusCode::PAYLOAD_TOO_LARGE),
        (post("/api/drives/nope/target", Some(TOKEN), ok_body), StatusCode::NOT_FOUND),
        (post("/api/drives/nope/reset", Some(TOKEN), ""), StatusCode::NOT_FOUND),
        (get("/api/history?drive=nope"), StatusCode::NOT_FOUND),
        (get("/api/history"), StatusCode::BAD_REQUEST),
        (get("/api/history?drive=pump1&seconds=abc"), StatusCode::BAD_REQUEST),
        (get("/api/history?drive=pump1&seconds=-3"), StatusCode::BAD_REQUEST),
        (get("/api/history?drive=pump1&seconds=inf"), StatusCode::BAD_REQUEST),
        (get("/api/recordings/..%2F..%2Fetc%2Fpasswd"), StatusCode::BAD_REQUEST),
        (get("/api/recordings/none-1.csv"), StatusCode::NOT_FOUND),
        // a segment that is not UTF-8: axum's plain-text 400 before
        (get("/api/drives/%ff/condition"), StatusCode::BAD_REQUEST),
        (get("/api/recordings/%ff.csv"), StatusCode::BAD_REQUEST),
        (post("/api/drives/%ff/target", Some(TOKEN), ok_body), StatusCode::BAD_REQUEST),
        (get("/no/such/route"), StatusCode::NOT_FOUND),
        (get("/readyz"), StatusCode::SERVICE_UNAVAILABLE),
    ];
    for (req, want) in cases {
        let what = format!("{} {}", req.method(), req.uri());
        let (status, json) = call(&app, req).await;
        assert_eq!(status, want, "{what}: {json}");
        if what != "GET /readyz" {
            assert!(json["error"].is_string(), "{what}: a JSON error body, got {json}");
        }
    }
    // infinity is a number above 0: the error says it must be finite too (it said "must be > 0, got inf")
    let (_, json) = call(&app, get("/api/history?drive=pump1&seconds=inf")).await;
    assert!(json["error"].as_str().is_some_and(|e| e.contains("finite")), "{json}");
    let (status, json) = call(&app, post(target, Some(TOKEN), ok_body)).await;
    assert_eq!(status, StatusCode::OK, "{json}");
    // the scheme in any case (RFC 9110): it was 401 for `bearer`
    let lower = Request::post(target)
        .header(header::CONTENT_TYPE, "application/json")
        .header(header::AUTHORIZATION, format!("bearer {TOKEN}"))
        .body(Body::from(ok_body))
        .expect("request");
    assert_eq!(call(&app, lower).await.0, StatusCode::OK);
    // a drive this router has never seen (no poll loop): a reset is refused, not kept for when the link comes
    let (status, json) = call(&app, post("/api/drives/pump1/reset", Some(TOKEN), "")).await;
    assert_eq!(status, StatusCode::CONFLICT, "{json}");
    assert!(json["error"].as_str().is_some_and(|e| e.contains("not seen")), "{json}");
    let (status, json) = call(&app, get("/api/status")).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(json["drives"][0]["target_omega_rad_s"], 30.0);
    assert_eq!(json["ready"], false);
    // status bodies are shared for up to a millisecond, but a write clears them: a client reads its own writes
    for t in [20.0, 25.0, 35.0] {
        let _ = call(&app, get("/api/status")).await;
        let (status, _) = call(&app, post(target, Some(TOKEN), format!(r#"{{"target_omega_rad_s": {t}}}"#))).await;
        assert_eq!(status, StatusCode::OK);
        let (_, json) = call(&app, get("/api/status")).await;
        assert_eq!(json["drives"][0]["target_omega_rad_s"], t);
    }
    assert_eq!(call(&app, get("/healthz")).await.0, StatusCode::OK);
    for uri in ["/api/status", "/api/history?drive=pump1&seconds=5"] {
        let resp = app.clone().oneshot(get(uri)).await.expect("infallible");
        assert_eq!(resp.headers()[header::CONTENT_TYPE], "application/json", "{uri}");
    }
    let page = app.clone().oneshot(get("/")).await.expect("infallible");
    assert_eq!(page.status(), StatusCode::OK);
    let html = axum::body::to_bytes(page.into_body(), usize::MAX).await.expect("body");
    assert!(String::from_utf8_lossy(&html).contains("uPlot.iife.min.js"));
    assert_eq!(app.clone().oneshot(get("/vendor/uPlot.iife.min.js")).await.expect("ok").status(), StatusCode::OK);
    stop.cancel();
}

#[tokio::test]
async fn write_routes_are_off_without_a_token_and_in_monitor_mode() {
    let (app, stop, _dir) = make_app(None, "speed");
    let (status, json) = call(&app, post("/api/drives/pump1/target", Some(""), r#"{"target_omega_rad_s": 1}"#)).await;
    assert_eq!(status, StatusCode::FORBIDDEN, "{json}");
    stop.cancel();
    let (app, stop, _dir) = make_app(Some(TOKEN), "monitor");
    let (status, _) = call(&app, post("/api/drives/pump1/target", Some(TOKEN), r#"{"target_omega_rad_s": 1}"#)).await;
    assert_eq!(status, StatusCode::CONFLICT);
    stop.cancel();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sse_delivers_snapshots_and_metrics_are_exposed() {
    let run = async {
        let stack = Stack::start(5.0, 10, "[drives.control]\nmode = \"manual\"\nfixed_hz = 10.0\n").await;
        wait_for(Duration::from_secs(15), || async { stack.state.ready() }).await.expect("fresh data");
        let resp = reqwest::get(format!("{}/api/events", stack.url)).await.expect("GET events");
        assert_eq!(resp.status(), 200);
        assert!(
            resp.headers()[reqwest::header::CONTENT_TYPE].to_str().expect("ascii").starts_with("text/event-stream")
        );
        let mut body = resp.bytes_stream();
        let (mut text, mut events, start) = (String::new(), 0, std::time::Instant::now());
        while events < 5 && start.elapsed() < Duration::from_secs(5) {
            let chunk = tokio::time::timeout(Duration::from_secs(2), body.next()).await.expect("an event within 2 s");
            text.push_str(&String::from_utf8_lossy(&chunk.expect("stream open").expect("bytes")));
            events = text.matches("event: snapshot").count();
        }
        assert!(events >= 5, "{text:.300}");
        let data = text.lines().find_map(|l| l.strip_prefix("data: ")).expect("data line");
        let snap: serde_json::Value = serde_json::from_str(data).expect("json");
        assert_eq!(snap["drives"][0]["name"], "pump1");
        assert_eq!(snap["drives"][0]["mode"], "manual");
        let elapsed = start.elapsed().as_secs_f64();
        assert!(elapsed < 1.5, "5 events at ≈10 Hz took {elapsed} s");
        drop(body);

        let m = stack.metrics().await;
        for name in [
            "hydrolens_polls_total{drive=\"pump1\"}",
            "hydrolens_reconnects_total",
            "hydrolens_stale{drive=\"pump1\"} 0",
            "hydrolens_link_up{drive=\"pump1\"} 1",
            "hydrolens_rejected_samples_total",
            "hydrolens_loop_period_seconds_bucket",
            "hydrolens_loop_jitter_p99_seconds{drive=\"pump1\"}",
            "hydrolens_omega_radians_per_second{drive=\"pump1\"}",
            "hydrolens_load_hat_newton_meters{drive=\"pump1\"}",
            "hydrolens_inertia_hat_kilogram_square_meters{drive=\"pump1\"}",
            "hydrolens_inertia_sd_kilogram_square_meters{drive=\"pump1\"}",
            "hydrolens_viscous_hat_newton_meter_seconds_per_radian{drive=\"pump1\"}",
            "hydrolens_viscous_sd_newton_meter_seconds_per_radian{drive=\"pump1\"}",
            "hydrolens_inertia_identified{drive=\"pump1\"}",
            "hydrolens_viscous_identified{drive=\"pump1\"}",
            "hydrolens_load_character{drive=\"pump1\"}",
            "hydrolens_setpoint_hertz{drive=\"pump1\"}",
            "hydrolens_inlet_pressure_pascals{drive=\"pump1\"}",
            "hydrolens_drive_frequency_hertz{drive=\"pump1\"}",
        ] {
            assert!(m.contains(name), "metrics lack {name}:\n{m}");
        }
        assert!(support::metric(&m, "hydrolens_polls_total{drive=\"pump1\"}").expect("polls") > 10.0);
        let ready = reqwest::get(format!("{}/readyz", stack.url)).await.expect("GET readyz");
        assert_eq!(ready.status(), 200);
        stack.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// One sample shape: the snapshot's `sample` holds the measured columns and `estimate` the estimates, no value in
/// both; the history's columns are the recording's, every one as long as `t_s`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_snapshot_carries_each_value_once_and_the_history_the_recording_columns() {
    use hydrolens::estimator::Estimate;
    use hydrolens::service::Measured;
    use hydrolens::service::state::COLUMNS;
    let run = async {
        let stack = Stack::start(5.0, 10, "[drives.control]\nmode = \"manual\"\nfixed_hz = 10.0\n").await;
        let rows = || stack.state.drives[0].history(5.0, 10_000).len();
        wait_for(Duration::from_secs(15), || async { stack.state.ready() && rows() > 20 }).await.expect("fresh data");
        let status = stack.status().await;
        let keys = |v: &serde_json::Value| {
            let mut k: Vec<String> = v.as_object().expect("an object").keys().cloned().collect();
            k.sort_unstable();
            k
        };
        let sorted = |c: &[&str]| {
            let mut k: Vec<String> = c.iter().map(|s| s.to_string()).collect();
            k.sort_unstable();
            k
        };
        assert_eq!(keys(&status["sample"]), sorted(&Measured::COLUMNS), "{status}");
        assert_eq!(keys(&status["estimate"]), sorted(&Estimate::COLUMNS), "{status}");
        assert!(status["status"]["word"].is_u64(), "the status word is in status: {status}");
        let h = support::get_json(format!("{}/api/history?drive=pump1&seconds=5", stack.url)).await;
        let mut want = sorted(&COLUMNS);
        want.push("drive".into());
        want.sort_unstable();
        assert_eq!(keys(&h), want);
        let n = h["t_s"].as_array().map_or(0, Vec::len);
        assert!(n > 10, "{n} rows");
        for c in COLUMNS {
            assert_eq!(h[c].as_array().map(Vec::len), Some(n), "{c}");
        }
        let f_set = h["f_set_hz"][n - 1].as_f64();
        assert!(
            f_set.is_some_and(|f| f > 0.0 && f <= 10.0),
            "the manual setpoint, written (ramping to 10 Hz): {f_set:?}"
        );
        stack.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(120), run).await.expect("bounded");
}

/// On a loopback address only requests naming a loopback host are answered: a web page elsewhere can point its own
/// name at 127.0.0.1 (DNS rebinding) and read the status and the recordings through the operator's browser; its
/// requests still name the page's host, and get 421. Over real TCP to the service as `serve` starts it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn on_loopback_only_requests_for_a_loopback_host_are_answered() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let run = async {
        let stack = Stack::start(5.0, 10, "").await;
        let addr = stack.url.trim_start_matches("http://").to_string();
        for (host, code) in [
            ("evil.example", "421"),
            ("evil.example:8080", "421"),
            ("127.0.0.1.evil.example", "421"),
            ("localhost:8080", "200"),
            ("LOCALHOST", "200"),
            ("127.0.0.1", "200"),
            ("[::1]:8080", "200"),
        ] {
            let mut c = tokio::net::TcpStream::connect(&addr).await.expect("connects");
            let request = format!("GET /api/status HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n");
            c.write_all(request.as_bytes()).await.expect("write");
            let mut reply = String::new();
            c.read_to_string(&mut reply).await.expect("read");
            let status = reply.split_whitespace().nth(1).unwrap_or("");
            assert_eq!(status, code, "Host: {host}: {reply}");
        }
        // every Host counts, and the host an absolute-form request line names (only the first header was looked at)
        for (head, code) in [
            ("GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\nHost: evil.example\r\n", "421"),
            ("GET http://evil.example/api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n", "421"),
            ("GET http://127.0.0.1/api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n", "200"),
            ("GET http://127.0.0.1:1@evil.example/api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n", "421"),
        ] {
            let mut c = tokio::net::TcpStream::connect(&addr).await.expect("connects");
            c.write_all(format!("{head}Connection: close\r\n\r\n").as_bytes()).await.expect("write");
            let mut reply = String::new();
            c.read_to_string(&mut reply).await.expect("read");
            let status = reply.split_whitespace().nth(1).unwrap_or("");
            assert_eq!(status, code, "{head:?}: {reply}");
        }
        // a reset with a body reads it before answering: the connection goes on (answered first, it was dropped
        // under the body still coming, and the next request on it failed)
        let mut c = tokio::net::TcpStream::connect(&addr).await.expect("connects");
        let body = "x".repeat(3000);
        let reset = format!(
            "POST /api/drives/pump1/reset HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {TOKEN}\r\n\
             Content-Length: {}\r\n\r\n",
            body.len()
        );
        c.write_all(reset.as_bytes()).await.expect("write");
        tokio::time::sleep(Duration::from_millis(50)).await; // the head first, as a client's socket sends it
        c.write_all(body.as_bytes()).await.expect("the body");
        c.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n").await.expect("next");
        let mut reply = String::new();
        c.read_to_string(&mut reply).await.expect("both answers");
        assert_eq!(reply.matches("HTTP/1.1 ").count(), 2, "two answers on one connection: {reply}");
        assert!(reply.contains("\"status\":\"ok\""), "{reply}");
        stack.stop().await;
    };
    tokio::time::timeout(Duration::from_secs(60), run).await.expect("bounded");
}
