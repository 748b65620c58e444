#!/usr/bin/env bash
# The README's test command: installs from Debian what the tests drive when it is missing (chromium for the dashboard
# test; prometheus (promtool) and python3-prometheus-client for the /metrics and alerting-rules tests; mosquitto for
# the MQTT tests, with mosquitto-clients (mosquitto_sub) and openssl for the TLS one; socat for the Modbus RTU tests'
# virtual serial line), then runs the whole suite. Extra arguments go to `cargo test` (e.g. `-- --ignored`).
set -euo pipefail
cd "$(dirname "$0")/.."
need=()
command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || need+=(chromium)
command -v promtool >/dev/null 2>&1 || need+=(prometheus)
[ -x /usr/sbin/mosquitto ] || command -v mosquitto >/dev/null 2>&1 || need+=(mosquitto)
command -v mosquitto_sub >/dev/null 2>&1 || need+=(mosquitto-clients)
command -v openssl >/dev/null 2>&1 || need+=(openssl)
# the OpenMetrics reference parser, for the /metrics test (Debian's python3, not a virtualenv's)
/usr/bin/python3 -c 'import prometheus_client.openmetrics.parser' >/dev/null 2>&1 || need+=(python3-prometheus-client)
command -v socat >/dev/null 2>&1 || need+=(socat)
if [ ${#need[@]} -gt 0 ]; then
  echo "tests/run.sh: installing ${need[*]} from Debian" >&2
  sudo_=""
  [ "$(id -u)" -eq 0 ] || sudo_="sudo"
  ($sudo_ apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo_ apt-get install -y -qq "${need[@]}" >/dev/null) \
    || echo "tests/run.sh: could not install ${need[*]}; the tests that drive them will fail" >&2
fi
# four test threads on two cores: most of the integration tests wait on a service's real time with the cores idle, so
# the suite takes about a quarter less time than with one thread a core (docs/development.md "Time in the tests");
# RUST_TEST_THREADS set outside wins
export RUST_TEST_THREADS="${RUST_TEST_THREADS:-4}"
exec cargo test --locked "$@"
