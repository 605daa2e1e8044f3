//! Where the `fbbus` binary under test is.

use std::path::Path;
use std::process::Command;
use std::sync::OnceLock;

/// The `fbbus` broker binary: next to the test executable's profile directory
/// (target/debug/deps/.. -> target/debug/fbbus), where cargo builds it for the broker's
/// own tests (it is their CARGO_BIN_EXE_fbbus) and `cargo test --workspace` for every
/// other crate's. If it is missing (one crate's tests run alone) it is built once.
pub fn fbbus_bin() -> &'static str {
    static BIN: OnceLock<String> = OnceLock::new();
    BIN.get_or_init(|| {
        let exe = std::env::current_exe().expect("the test executable's path");
        let profile_dir = exe
            .parent()
            .and_then(Path::parent)
            .expect("the test executable lives in <target>/<profile>/deps");
        let bin = profile_dir.join("fbbus");
        let path = || bin.to_str().expect("a UTF-8 target directory").to_owned();
        if bin.is_file() {
            return path();
        }
        eprintln!(
            "{} is missing: building it with `cargo build -p broker --bin fbbus` (once)",
            bin.display()
        );
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../Cargo.toml");
        let mut cmd = Command::new(cargo);
        cmd.args(["build", "-p", "broker", "--bin", "fbbus", "--manifest-path"])
            .arg(&manifest);
        if let Some(target_dir) = profile_dir.parent() {
            cmd.arg("--target-dir").arg(target_dir);
        }
        if profile_dir.file_name().is_some_and(|n| n == "release") {
            cmd.arg("--release");
        }
        let status = cmd
            .status()
            .unwrap_or_else(|e| panic!("cannot run {cmd:?}: {e}"));
        assert!(
            status.success() && bin.is_file(),
            "`cargo build -p broker --bin fbbus` failed ({status}); build the broker first \
             (`cargo build -p broker`) so that {} exists",
            bin.display()
        );
        path()
    })
}
