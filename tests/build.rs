//! Sets `cfg(browser_tools)` when the dashboard's browser test can run here: Chromium
//! (`$PATHFARM_CHROMIUM` or /usr/bin/chromium), `node` on PATH and playwright-core in
//! tests/browser/node_modules (`npm ci` there). Without them the test is `#[ignore]`d with that
//! reason instead of passing without running; `scripts/test` installs them first.
//! Likewise `cfg(slurm_tools)` when munge and Slurm's daemons and `sbatch` are installed.
//! Likewise `cfg(bpy)`: `python3` imports `bpy` (Blender as a module), OpenEXR and numpy, for the
//! Blender add-on's tests; `cfg(openapi_client)`: `openapi-python-client` is on PATH.

use std::path::{Path, PathBuf};
use std::process::Command;

fn main() {
    println!("cargo:rustc-check-cfg=cfg(browser_tools)");
    println!("cargo:rustc-check-cfg=cfg(slurm_tools)");
    println!("cargo:rerun-if-env-changed=PATHFARM_CHROMIUM");
    println!("cargo:rerun-if-env-changed=PATH");
    let chromium =
        std::env::var_os("PATHFARM_CHROMIUM").map_or_else(|| PathBuf::from("/usr/bin/chromium"), PathBuf::from);
    let playwright = Path::new("browser/node_modules/playwright-core/package.json");
    // A missing path here makes cargo run this script again on every build, so installing the
    // tools later is noticed.
    println!("cargo:rerun-if-changed={}", chromium.display());
    println!("cargo:rerun-if-changed={}", playwright.display());
    let node = Command::new("node").arg("--version").output().is_ok_and(|o| o.status.success());
    if chromium.exists() && playwright.exists() && node {
        println!("cargo:rustc-cfg=browser_tools");
    }
    // The Slurm test (tests/tests/slurm.rs): a single-node cluster from Debian's packages.
    let slurm = ["/usr/sbin/munged", "/usr/sbin/slurmctld", "/usr/sbin/slurmd", "/usr/bin/sbatch"];
    for p in slurm {
        println!("cargo:rerun-if-changed={p}");
    }
    if slurm.iter().all(|p| Path::new(p).exists()) {
        println!("cargo:rustc-cfg=slurm_tools");
    }
    // `cfg(oidn)`: OIDN is here (`OIDN_DIR` names pyoidn's folder with the library), as
    // scripts/test and .ci/run set it when they build with `--features pathfarm-worker/denoise`;
    // the farm's denoise bit-identity test needs workers built so, and is ignored without it.
    println!("cargo:rustc-check-cfg=cfg(oidn)");
    println!("cargo:rerun-if-env-changed=OIDN_DIR");
    if std::env::var_os("OIDN_DIR").is_some_and(|d| Path::new(&d).join("lib/libOpenImageDenoise.so").exists()) {
        println!("cargo:rustc-cfg=oidn");
    }
    println!("cargo:rustc-check-cfg=cfg(bpy)");
    println!("cargo:rustc-check-cfg=cfg(openapi_client)");
    println!("cargo:rerun-if-env-changed=PATHFARM_RECHECK_PYTHON");
    // Without LD_LIBRARY_PATH, as the tests run Python (an OIDN folder there breaks `import bpy`).
    let python = |code: &str| {
        Command::new("python3")
            .args(["-c", code])
            .env_remove("LD_LIBRARY_PATH")
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if python("import bpy, OpenEXR, numpy") {
        println!("cargo:rustc-cfg=bpy");
    }
    let generator = Command::new("openapi-python-client").arg("--version").output().is_ok_and(|o| o.status.success());
    if generator && python("import httpx, attrs") {
        println!("cargo:rustc-cfg=openapi_client");
    }
}
