//! Secrets stay out of logs: a coordinator that generates its tokens on the first start, with
//! stderr going to a file (as under systemd, where it is the journal), writes them only to
//! DATA_DIR/tokens.json (mode 0600), never to its log.

mod support;

use std::os::unix::fs::PermissionsExt;
use std::process::{Command, Stdio};
use std::time::Duration;
use support::*;

/// `pathfarm-coordinator --listen 127.0.0.1:0 --data-dir DATA EXTRA...` with no token in the
/// environment (so it generates or reads its own).
fn coordinator(data: &std::path::Path, extra: &[&std::ffi::OsStr]) -> Command {
    let mut cmd = Command::new(bin("pathfarm-coordinator"));
    cmd.args(["--listen", "127.0.0.1:0", "--data-dir"])
        .arg(data)
        .args(extra)
        .env_remove("PATHFARM_CLIENT_TOKEN")
        .env_remove("PATHFARM_WORKER_TOKEN")
        .stdout(Stdio::null());
    cmd
}

fn wait_listening(data: &std::path::Path) -> String {
    wait_for("the coordinator to listen", Duration::from_secs(30), || {
        std::fs::read_to_string(data.join("coordinator.addr")).ok().filter(|a| !a.is_empty())
    })
}

#[test]
fn generated_tokens_are_not_logged() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    let log_path = dir.path().join("coordinator.log");
    let log = std::fs::File::create(&log_path).expect("log");
    let child = coordinator(&data, &[]).env("RUST_LOG", "info").stderr(log).spawn().expect("spawn");
    let _coordinator = Proc { child };
    let tokens: serde_json::Value = wait_for("tokens.json", Duration::from_secs(30), || {
        serde_json::from_slice(&std::fs::read(data.join("tokens.json")).ok()?).ok()
    });
    wait_listening(&data);
    let mode = std::fs::metadata(data.join("tokens.json")).expect("meta").permissions().mode() & 0o777;
    assert_eq!(mode, 0o600, "tokens.json must be private");
    let log = std::fs::read_to_string(&log_path).expect("read log");
    for key in ["client_token", "worker_token"] {
        let token = tokens[key].as_str().expect("token");
        assert!(token.len() >= 32, "{key} too short");
        assert!(!log.contains(token), "the {key} is in the log:\n{log}");
    }
    assert!(log.contains("tokens.json"), "the log should say where the tokens are:\n{log}");
}

/// Tokens read from files (`--client-token-file`, `--worker-token-file`: no secret in argv or
/// the environment), and `pathfarm-coordinator healthcheck` for container health checks.
#[test]
fn token_files_and_the_healthcheck_subcommand() {
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    let (client_file, worker_file) = (dir.path().join("client"), dir.path().join("worker"));
    std::fs::write(&client_file, "client-secret-from-a-file-0123456789\n").expect("write");
    std::fs::write(&worker_file, "worker-secret-from-a-file-0123456789\n").expect("write");
    let files = [
        "--client-token-file".as_ref(),
        client_file.as_os_str(),
        "--worker-token-file".as_ref(),
        worker_file.as_os_str(),
    ];
    let child = coordinator(&data, &files).stderr(Stdio::null()).spawn().expect("spawn");
    let _coordinator = Proc { child };
    let addr = wait_listening(&data);
    let url = format!("http://{addr}");
    let healthcheck = |url: &str| {
        let mut cmd = Command::new(bin("pathfarm-coordinator"));
        cmd.args(["healthcheck", "--url", url]).stderr(Stdio::null()).status().expect("healthcheck")
    };
    wait_for("the healthcheck to pass", Duration::from_secs(30), || healthcheck(&url).success().then_some(()));
    let http = reqwest::blocking::Client::new();
    let jobs = format!("{url}/api/v1/jobs");
    assert_eq!(http.get(&jobs).send().expect("GET").status(), reqwest::StatusCode::UNAUTHORIZED);
    let ok = http.get(&jobs).bearer_auth("client-secret-from-a-file-0123456789").send().expect("GET");
    assert_eq!(ok.status(), reqwest::StatusCode::OK);
    // Nothing listens on the port of a closed listener.
    let closed = std::net::TcpListener::bind("127.0.0.1:0").expect("bind").local_addr().expect("addr");
    assert!(!healthcheck(&format!("http://{closed}")).success(), "the healthcheck passed with no coordinator");
    // An empty token file is refused at start-up.
    std::fs::write(&client_file, "\n").expect("write");
    let out = coordinator(&dir.path().join("data2"), &files).output().expect("run");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("is empty"), "{}", String::from_utf8_lossy(&out.stderr));
}
