#!/usr/bin/env bash
# Fuzz the REST API with schemathesis (https://schemathesis.readthedocs.io), driven by the
# coordinator's own OpenAPI document at /api/v1/openapi.json.
#
# Usage:
#   scripts/fuzz-api.sh                 # starts target/release/pathfarm-coordinator on a free port
#   scripts/fuzz-api.sh http://HOST:PORT   # fuzzes a coordinator that is already running
#
# Environment:
#   COORDINATOR_BIN   coordinator binary (default: target/release/pathfarm-coordinator)
#   MAX_EXAMPLES      examples per operation (default 50)
#   SEED              schemathesis seed (default 20261129, for reproducible runs)
#   MAX_TIME          overall time budget in seconds (default 300)
#   CHECKS            schemathesis checks (default: all)
#   EXCLUDE_CHECKS    checks to skip (default: none)
#   SCHEMATHESIS      schemathesis executable (default: a venv in target/schemathesis-venv,
#                     created with pip on first use; SCHEMATHESIS_VERSION pins it, default 4.32.5)
#   REPORT_DIR        where the JUnit report goes (default: target/fuzz-api)
#   CLIENT_TOKEN, WORKER_TOKEN
#                     bearer tokens. A coordinator started here gets --client-token and
#                     --worker-token (defaults fuzz-client / fuzz-worker); schemathesis sends
#                     each to the operations whose security scheme (client_token, worker_token)
#                     asks for it, and checks that missing or wrong tokens are refused.
#
# With no /api/v1/openapi.json (404), the script says so and exits 0 without fuzzing (SKIP),
# so it can sit in CI before the endpoint lands. A 5xx, a schema violation or any other
# failed check exits non-zero.
set -euo pipefail

root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"

max_examples="${MAX_EXAMPLES:-50}"
seed="${SEED:-20261129}"
max_time="${MAX_TIME:-300}"
checks="${CHECKS:-all}"
report_dir="${REPORT_DIR:-$root/target/fuzz-api}"
st_version="${SCHEMATHESIS_VERSION:-4.32.5}"
client_token="${CLIENT_TOKEN:-fuzz-client}"
worker_token="${WORKER_TOKEN:-fuzz-worker}"

# --- schemathesis --------------------------------------------------------------------------
st="${SCHEMATHESIS:-}"
if [[ -z "$st" ]]; then
    venv="$root/target/schemathesis-venv"
    if [[ ! -x "$venv/bin/schemathesis" ]]; then
        echo "fuzz-api: installing schemathesis $st_version into $venv" >&2
        python3 -m venv "$venv"
        "$venv/bin/pip" install --quiet "schemathesis==$st_version"
    fi
    st="$venv/bin/schemathesis"
fi

# --- coordinator ---------------------------------------------------------------------------
data_dir=""
pid=""
cleanup() {
    if [[ -n "$pid" ]]; then
        kill "$pid" 2>/dev/null || true
        wait "$pid" 2>/dev/null || true
    fi
    if [[ -n "$data_dir" ]]; then
        rm -rf "$data_dir"
    fi
}
trap cleanup EXIT

if [[ $# -ge 1 ]]; then
    base="${1%/}"
else
    bin="${COORDINATOR_BIN:-$root/target/release/pathfarm-coordinator}"
    if [[ ! -x "$bin" ]]; then
        echo "fuzz-api: $bin is missing: cargo build --release -p pathfarm-coordinator" >&2
        exit 1
    fi
    data_dir="$(mktemp -d)"
    extra=(--client-token "$client_token" --worker-token "$worker_token")
    # A small upload limit keeps generated bodies cheap (older binaries lack the flag).
    if "$bin" --help 2>/dev/null | grep -q -- --max-upload-mb; then
        extra+=(--max-upload-mb 4)
    fi
    RUST_LOG=warn "$bin" --listen 127.0.0.1:0 --data-dir "$data_dir" "${extra[@]}" \
        2>"$data_dir/coordinator.log" &
    pid=$!
    for _ in $(seq 200); do
        [[ -s "$data_dir/coordinator.addr" ]] && break
        if ! kill -0 "$pid" 2>/dev/null; then
            echo "fuzz-api: the coordinator exited:" >&2
            cat "$data_dir/coordinator.log" >&2
            exit 1
        fi
        sleep 0.05
    done
    base="http://$(cat "$data_dir/coordinator.addr")"
fi

schema="$base/api/v1/openapi.json"
status="$(curl -s -o /dev/null -w '%{http_code}' -H "Authorization: Bearer $client_token" "$schema" || true)"
if [[ "$status" == "404" ]]; then
    echo "fuzz-api: SKIP: $schema does not exist yet (404); nothing to fuzz"
    exit 0
fi
if [[ "$status" != "200" ]]; then
    echo "fuzz-api: $schema answered $status" >&2
    exit 1
fi

# A scene, so that job creation can get past "scene not uploaded" now and then.
curl -s -o /dev/null -H "Authorization: Bearer $client_token" --data-binary '{"asset":{"version":"2.0"}}' \
    "$base/api/v1/scenes" || true

mkdir -p "$report_dir"
config="$report_dir/schemathesis.toml"
cat >"$config" <<EOF
[auth.openapi.client_token]
bearer = "$client_token"

[auth.openapi.worker_token]
bearer = "$worker_token"
EOF
args=(--config-file "$config" run "$schema" --url "$base"
    --checks "$checks"
    --max-examples "$max_examples"
    --seed "$seed"
    --max-time "$max_time"
    --request-timeout 30
    --workers 2
    --report junit --report-dir "$report_dir")
if [[ -n "${EXCLUDE_CHECKS:-}" ]]; then
    args+=(--exclude-checks "$EXCLUDE_CHECKS")
fi
echo "fuzz-api: $st ${args[*]}" >&2
set +e
# schemathesis keeps its example database in ./.schemathesis: keep it under the report dir.
(cd "$report_dir" && "$st" "${args[@]}")
rc=$?
set -e
if [[ -n "$pid" ]] && ! kill -0 "$pid" 2>/dev/null; then
    echo "fuzz-api: the coordinator died during the run:" >&2
    cat "$data_dir/coordinator.log" >&2
    exit 1
fi
if [[ -n "$pid" ]]; then
    # Still serving after the fuzzing?
    curl -sf "$base/healthz" >/dev/null || { echo "fuzz-api: /healthz fails after the run" >&2; exit 1; }
fi
exit "$rc"
