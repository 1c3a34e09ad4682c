//! Python test peers (PyPI packages that `.ci/run` installs): whether they can run here.

use std::process::Command;

/// True when `CI` is set (not empty, 0 or false).
pub fn in_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| !v.is_empty() && v != "0" && v != "false")
}

/// True if `python3 -c "<imports>"` works. Otherwise shouts that `test` did NOT run and how to
/// make it run (`install`), and fails in CI, where the packages must be there.
pub fn python_can_import(imports: &str, test: &str, install: &str) -> bool {
    let probe = Command::new("python3").args(["-c", imports]).output();
    let why = match probe {
        Ok(o) if o.status.success() => return true,
        Ok(o) => String::from_utf8_lossy(&o.stderr).trim().to_string(),
        Err(e) => format!("cannot run python3: {e}"),
    };
    let msg = format!(
        "\n!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n\
         !!! {test}: the Python packages are not usable:\n!!! {why}\n\
         !!! This test did NOT run ({install}).\n\
         !!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n"
    );
    if in_ci() {
        panic!("{msg}(CI is set: this is a failure)");
    }
    eprintln!("{msg}");
    false
}
