//! The config's `[mqtt]` section (CONTRACT.md "Extensions"), parsed raw and validated at load with the rest of the
//! config ([`super`] reads it): the broker's URL, the topics, the pacing and queue, the credentials, and the TLS
//! client of `mqtts://`. The publisher ([`crate::mqtt`], an outlet above the service) is handed the result.
//!
//! It uses no other module of the service.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
use serde::Deserialize;

use crate::error::KeyError;

/// `[mqtt]` as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawMqtt {
    url: String,
    #[serde(default = "default_prefix")]
    topic_prefix: String,
    #[serde(default = "default_interval")]
    interval_ms: u64,
    username: Option<String>,
    password: Option<String>,
    /// Default `hydrolens-<pid>`; two services on one broker need different ids.
    client_id: Option<String>,
    /// Messages waiting for the broker at most; past it the oldest is dropped (and counted).
    #[serde(default = "default_queue")]
    queue_messages: usize,
    /// mqtts:// only: PEM of the CA(s) that signed the broker's certificate; absent: the system's roots.
    ca_file: Option<String>,
    /// mqtts:// only, both or neither: a client certificate (PEM, chain) and its key, for brokers that ask for one.
    client_cert_file: Option<String>,
    client_key_file: Option<String>,
}

fn default_prefix() -> String {
    "hydrolens".into()
}
fn default_interval() -> u64 {
    1000
}
fn default_queue() -> usize {
    1000
}

/// The bounds of `mqtt.interval_ms`: 10 messages a second per drive at most, one an hour at least.
pub const INTERVAL_MS: std::ops::RangeInclusive<u64> = 100..=3_600_000;
/// The bounds of `mqtt.queue_messages`.
pub const QUEUE_MESSAGES: std::ops::RangeInclusive<usize> = 1..=100_000;

/// Validated `[mqtt]`.
#[derive(Debug, Clone)]
pub struct MqttSettings {
    /// As written, for `/api/status` and the logs (credentials are never in it).
    pub url: String,
    pub host: String,
    pub port: u16,
    pub topic_prefix: String,
    pub interval: Duration,
    /// Username and password, both or neither. Never logged.
    pub credentials: Option<(String, String)>,
    pub client_id: String,
    pub queue_messages: usize,
    /// mqtts://: the TLS client built at load (roots, client certificate); `None` for mqtt://.
    pub tls: Option<Arc<rustls::ClientConfig>>,
}

/// `mqtt://host[:port]` (port 1883 by default) or `mqtts://host[:port]` (TLS, port 8883 by default) into TLS or
/// not, host and port.
/// `url` quoted for a message, what stands before its last `@` (credentials) left out: the message goes to the
/// journal, and the check that keeps credentials out of the URL echoed them.
fn without_credentials(url: &str) -> String {
    match (url.rsplit_once('@'), url.split_once("://")) {
        (Some((_, host)), Some((scheme, _))) => format!("\"{scheme}://…@{host}\""),
        (Some((_, host)), None) => format!("\"…@{host}\""),
        (None, _) => format!("{url:?}"),
    }
}

fn parse_url(url: &str) -> Result<(bool, String, u16), String> {
    let lower = url.to_ascii_lowercase();
    let (tls, rest) = if lower.starts_with("mqtt://") {
        (false, &url["mqtt://".len()..])
    } else if lower.starts_with("mqtts://") {
        (true, &url["mqtts://".len()..])
    } else {
        return Err(format!(
            "{} is not a URL such as mqtt://127.0.0.1:1883 or mqtts://broker.plant:8883",
            without_credentials(url)
        ));
    };
    let rest = rest.strip_suffix('/').unwrap_or(rest);
    if rest.contains('@') {
        return Err(format!(
            "{}: put credentials in mqtt.username and mqtt.password, not in the URL (not repeated here)",
            without_credentials(url)
        ));
    }
    if rest.contains(['/', '?', '#']) {
        return Err(format!("{url:?}: a broker URL has no path or query (mqtt://host:port)"));
    }
    let (host, port) = if let Some(v6) = rest.strip_prefix('[') {
        let (h, tail) = v6.split_once(']').ok_or_else(|| format!("{url:?}: unclosed [ in the host"))?;
        (h, tail.strip_prefix(':'))
    } else {
        match rest.rsplit_once(':') {
            Some((h, p)) => (h, Some(p)),
            None => (rest, None),
        }
    };
    if host.is_empty() || (host.contains([':', ' ']) && !rest.starts_with('[')) {
        return Err(format!("{url:?}: no host"));
    }
    let port = match port {
        None if tls => 8883,
        None => 1883,
        Some(p) => {
            p.parse().ok().filter(|p| *p > 0).ok_or_else(|| format!("{url:?}: port {p:?} is not 1 ..= 65535"))?
        }
    };
    Ok((tls, host.to_string(), port))
}

/// The PEM certificates in `path` (read for the key `key`); at least one.
fn read_certs(key: &str, path: &Path) -> Result<Vec<CertificateDer<'static>>, KeyError> {
    let pem = crate::error::read_small_file(path)
        .map_err(|e| KeyError::new(key.to_string(), format!("{}: {e}", path.display())))?;
    let certs = CertificateDer::pem_slice_iter(&pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| KeyError::new(key.to_string(), format!("{}: not PEM certificates: {e}", path.display())))?;
    if certs.is_empty() {
        return Err(KeyError::new(
            key.to_string(),
            format!("{}: no PEM certificate (-----BEGIN CERTIFICATE-----) in it", path.display()),
        ));
    }
    Ok(certs)
}

/// The TLS client of `mqtts://`: roots from `ca_file` or the system's, a client certificate if given. Every file is
/// read and checked here, at load, so that a mistyped one stops the service with its key's name.
fn tls_config(ca_file: Option<&Path>, client: Option<(&Path, &Path)>) -> Result<rustls::ClientConfig, KeyError> {
    let k = |s: &str| format!("mqtt.{s}");
    let mut roots = rustls::RootCertStore::empty();
    match ca_file {
        Some(path) => {
            for (i, cert) in read_certs(&k("ca_file"), path)?.into_iter().enumerate() {
                roots.add(cert).map_err(|e| {
                    KeyError::new(
                        k("ca_file"),
                        format!("{}: certificate {} is not a CA certificate: {e}", path.display(), i + 1),
                    )
                })?;
            }
        }
        None => {
            let found = rustls_native_certs::load_native_certs();
            let (added, _) = roots.add_parsable_certificates(found.certs);
            if added == 0 {
                let errors: Vec<String> = found.errors.iter().map(|e| e.to_string()).collect();
                return Err(KeyError::new(
                    k("ca_file"),
                    format!(
                        "is not given and the system has no CA certificates ({}); name the broker's CA in mqtt.ca_file, \
                         or install the system's (Debian: ca-certificates)",
                        if errors.is_empty() { "none found".to_string() } else { errors.join("; ") }
                    ),
                ));
            }
        }
    }
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| KeyError::new(k("url"), format!("TLS: {e}")))?
        .with_root_certificates(roots);
    match client {
        None => Ok(builder.with_no_client_auth()),
        Some((cert_path, key_path)) => {
            let chain = read_certs(&k("client_cert_file"), cert_path)?;
            let key_pem = crate::error::read_small_file(key_path)
                .map_err(|e| KeyError::new(k("client_key_file"), format!("{}: {e}", key_path.display())))?;
            let key = PrivateKeyDer::from_pem_slice(&key_pem).map_err(|e| {
                KeyError::new(k("client_key_file"), format!("{}: no PEM private key: {e}", key_path.display()))
            })?;
            builder.with_client_auth_cert(chain, key).map_err(|e| {
                KeyError::new(
                    k("client_key_file"),
                    format!("{}: does not go with mqtt.client_cert_file: {e}", key_path.display()),
                )
            })
        }
    }
}

/// Validates `[mqtt]`; errors name the key. `resolve` turns a file name as written into a path (relative ones as the
/// config's model paths are).
pub fn validate(raw: RawMqtt, resolve: impl Fn(&str) -> PathBuf) -> Result<MqttSettings, KeyError> {
    let k = |s: &str| format!("mqtt.{s}");
    let (tls, host, port) = parse_url(raw.url.trim()).map_err(|m| KeyError::new(k("url"), m))?;
    let prefix = raw.topic_prefix;
    if prefix.is_empty() || prefix.starts_with('/') || prefix.ends_with('/') || prefix.contains(['+', '#', '\0']) {
        return Err(KeyError::new(
            k("topic_prefix"),
            format!("{prefix:?} must be a topic without wildcards (+, #) and without a leading or trailing /"),
        ));
    }
    if !INTERVAL_MS.contains(&raw.interval_ms) {
        return Err(KeyError::new(k("interval_ms"), format!("must be 100 ..= 3600000, got {}", raw.interval_ms)));
    }
    if !QUEUE_MESSAGES.contains(&raw.queue_messages) {
        return Err(KeyError::new(k("queue_messages"), format!("must be 1 ..= 100000, got {}", raw.queue_messages)));
    }
    let credentials = match (raw.username, raw.password) {
        (Some(u), Some(p)) => Some((u, p)),
        (None, None) => None,
        (Some(_), None) => return Err(KeyError::new(k("password"), "is needed with mqtt.username".into())),
        (None, Some(_)) => return Err(KeyError::new(k("username"), "is needed with mqtt.password".into())),
    };
    let client_id = raw.client_id.unwrap_or_else(|| format!("hydrolens-{}", std::process::id()));
    if client_id.is_empty() || client_id.len() > 65535 {
        return Err(KeyError::new(k("client_id"), "must not be empty".into()));
    }
    let files = [
        ("ca_file", &raw.ca_file),
        ("client_cert_file", &raw.client_cert_file),
        ("client_key_file", &raw.client_key_file),
    ];
    if !tls && let Some((key, _)) = files.iter().find(|(_, f)| f.is_some()) {
        return Err(KeyError::new(k(key), "is for TLS: the broker's URL (mqtt.url) would be mqtts://".into()));
    }
    let client = match (raw.client_cert_file, raw.client_key_file) {
        (Some(c), Some(key)) => Some((resolve(&c), resolve(&key))),
        (None, None) => None,
        (Some(_), None) => {
            return Err(KeyError::new(k("client_key_file"), "is needed with mqtt.client_cert_file".into()));
        }
        (None, Some(_)) => {
            return Err(KeyError::new(k("client_cert_file"), "is needed with mqtt.client_key_file".into()));
        }
    };
    let tls = if tls {
        ServerName::try_from(host.as_str()).map_err(|_| {
            KeyError::new(
                k("url"),
                format!("{host:?} is neither a DNS name nor an IP address to check the certificate against"),
            )
        })?;
        let ca_file = raw.ca_file.map(|p| resolve(&p));
        let client = client.as_ref().map(|(c, key)| (c.as_path(), key.as_path()));
        Some(Arc::new(tls_config(ca_file.as_deref(), client)?))
    } else {
        None
    };
    Ok(MqttSettings {
        url: raw.url.trim().to_string(),
        host,
        port,
        topic_prefix: prefix,
        interval: Duration::from_millis(raw.interval_ms),
        credentials,
        client_id,
        queue_messages: raw.queue_messages,
        tls,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raw(text: &str) -> RawMqtt {
        toml::from_str(text).expect("parses")
    }

    fn settings(text: &str) -> Result<MqttSettings, KeyError> {
        validate(raw(text), |p: &str| PathBuf::from(p))
    }

    fn err(text: &str) -> KeyError {
        settings(text).expect_err("invalid")
    }

    #[test]
    fn urls_and_bounds() {
        let s = settings("url = \"mqtt://127.0.0.1:1884\"\n").expect("valid");
        assert_eq!((s.host.as_str(), s.port, s.topic_prefix.as_str()), ("127.0.0.1", 1884, "hydrolens"));
        assert_eq!(s.interval, Duration::from_secs(1));
        let s = settings("url = \"mqtt://broker.plant/\"\n").expect("valid");
        assert_eq!((s.host.as_str(), s.port), ("broker.plant", 1883));
        let s = settings("url = \"mqtt://[::1]:1883\"\n").expect("valid");
        assert_eq!(s.host, "::1");
        for bad in ["ssl://b:8883", "http://b", "mqtt://", "mqtt://b:0", "mqtt://b:x", "mqtt://u:p@b", "mqtt://b/x"] {
            let KeyError { key, message } = err(&format!("url = \"{bad}\"\n"));
            assert_eq!(key, "mqtt.url", "{bad}: {message}");
        }
        assert_eq!(parse_url("mqtts://broker.plant"), Ok((true, "broker.plant".into(), 8883)));
        assert_eq!(parse_url("MQTTS://10.0.0.5:8884"), Ok((true, "10.0.0.5".into(), 8884)));
        assert_eq!(parse_url("mqtt://10.0.0.5"), Ok((false, "10.0.0.5".into(), 1883)));
        assert_eq!(err("url = \"mqtt://b\"\ninterval_ms = 10\n").key, "mqtt.interval_ms");
        assert_eq!(err("url = \"mqtt://b\"\ninterval_ms = 4000000\n").key, "mqtt.interval_ms");
        assert_eq!(err("url = \"mqtt://b\"\nqueue_messages = 0\n").key, "mqtt.queue_messages");
        assert_eq!(err("url = \"mqtt://b\"\ntopic_prefix = \"a/#\"\n").key, "mqtt.topic_prefix");
        assert_eq!(err("url = \"mqtt://b\"\ntopic_prefix = \"/a\"\n").key, "mqtt.topic_prefix");
        assert_eq!(err("url = \"mqtt://b\"\nusername = \"u\"\n").key, "mqtt.password");
        let s = settings("url = \"mqtt://b\"\nusername = \"u\"\npassword = \"p\"\n").expect("valid");
        assert_eq!(s.credentials, Some(("u".into(), "p".into())));
    }

    /// The TLS keys are refused at load naming the key (and the file); a working mqtts:// is tests/it/mqtt.rs's.
    #[test]
    fn tls_files_are_checked_at_load() {
        let dir = tempfile::tempdir().expect("tmp");
        let not_pem = dir.path().join("ca.txt");
        std::fs::write(&not_pem, "just some text\n").expect("write");
        let bad_pem = dir.path().join("bad.pem");
        std::fs::write(&bad_pem, "-----BEGIN CERTIFICATE-----\n!!!\n-----END CERTIFICATE-----\n").expect("write");
        let missing = dir.path().join("missing.pem");
        for (file, text) in [(&not_pem, "no PEM certificate"), (&bad_pem, ""), (&missing, "")] {
            let KeyError { key, message } =
                err(&format!("url = \"mqtts://127.0.0.1\"\nca_file = {:?}\n", file.display().to_string()));
            assert_eq!(key, "mqtt.ca_file", "{message}");
            assert!(message.contains(&file.display().to_string()) && message.contains(text), "{message}");
        }
        let KeyError { key, message } = err("url = \"mqtts://b\"\nclient_cert_file = \"c.pem\"\n");
        assert_eq!(key, "mqtt.client_key_file", "{message}");
        assert_eq!(err("url = \"mqtts://b\"\nclient_key_file = \"k.pem\"\n").key, "mqtt.client_cert_file");
        let KeyError { key, message } = err("url = \"mqtt://b\"\nca_file = \"ca.pem\"\n");
        assert_eq!(key, "mqtt.ca_file");
        assert!(message.contains("mqtts://"), "{message}");
        let client = "client_cert_file = \"c.pem\"\nclient_key_file = \"k.pem\"\n";
        assert_eq!(err(&format!("url = \"mqtt://b\"\n{client}")).key, "mqtt.client_cert_file");
        assert_eq!(err("url = \"mqtt://b\"\nclient_key_file = \"k.pem\"\n").key, "mqtt.client_key_file");
        assert_eq!(err("url = \"mqtts://a..b\"\n").key, "mqtt.url");
    }
}
