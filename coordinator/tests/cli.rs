//! The coordinator and client binaries as processes: bad flags are refused with a message.

use std::process::Command;

#[test]
fn coordinator_refuses_a_bad_listen_address() {
    let out = Command::new(env!("CARGO_BIN_EXE_pathfarm-coordinator"))
        .args(["--listen", "not-an-address"])
        .output()
        .expect("run");
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--listen"));
}

#[test]
fn client_reports_an_unreachable_coordinator() {
    let out = Command::new(env!("CARGO_BIN_EXE_pathfarm"))
        .args(["--server", "http://127.0.0.1:9", "status"])
        .output()
        .expect("run");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cannot reach the coordinator"), "{err}");
}
