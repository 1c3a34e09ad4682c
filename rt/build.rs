//! Builds `chunkrt_ruckig`: an allocation-free C shim (`ffi/`) over the official ruckig C++
//! sources shipped by the `ruckig` crate (located with `cargo metadata`).
//! Only the local (non-cloud) sources are compiled; the namespace is renamed so the symbols
//! never clash with the `ruckig` crate's own static library in binaries that link both.

use std::path::PathBuf;
use std::process::Command;

fn ruckig_root() -> Result<PathBuf, String> {
    if let Ok(dir) = std::env::var("CHUNKRT_RUCKIG_DIR") {
        return Ok(PathBuf::from(dir));
    }
    // Offline first (the usual case: cargo has already fetched the dependencies). The platform
    // filter matters: without it cargo metadata wants every package of the lock file, Windows-only
    // ones included, which a Linux machine never downloads. Then online, because `ruckig` is a
    // dev-dependency that a plain `cargo build` on a fresh machine has not fetched yet.
    let mut errors = Vec::new();
    for offline in [true, false] {
        match metadata(offline).and_then(|text| find_ruckig(&text)) {
            Ok(dir) => return Ok(dir),
            Err(e) => errors.push(e),
        }
    }
    Err(errors.join("; "))
}

/// `cargo metadata` for the target platform.
fn metadata(offline: bool) -> Result<String, String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".to_string());
    let manifest_dir = std::env::var("CARGO_MANIFEST_DIR").map_err(|e| e.to_string())?;
    let target = std::env::var("TARGET").map_err(|e| e.to_string())?;
    let mut cmd = Command::new(cargo);
    cmd.args([
        "metadata",
        "--format-version",
        "1",
        "--filter-platform",
        &target,
    ])
    .current_dir(&manifest_dir);
    if offline {
        cmd.arg("--offline");
    }
    let out = cmd
        .output()
        .map_err(|e| format!("cannot run cargo metadata: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "cargo metadata{} failed: {}",
            if offline { " --offline" } else { "" },
            String::from_utf8_lossy(&out.stderr).trim()
        ));
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// The `ruckig` package's directory in `cargo metadata` output, without a JSON dependency:
/// packages are objects with "name":"ruckig" followed (in the same object) by
/// "manifest_path":"...".
fn find_ruckig(text: &str) -> Result<PathBuf, String> {
    let mut rest: &str = text;
    while let Some(i) = rest.find("\"name\":\"ruckig\"") {
        rest = &rest[i + 15..];
        let Some(m) = rest.find("\"manifest_path\":\"") else {
            break;
        };
        let after = &rest[m + 17..];
        let Some(end) = after.find('"') else { break };
        let manifest = PathBuf::from(&after[..end]);
        if manifest.ends_with("Cargo.toml") && manifest.to_string_lossy().contains("ruckig") {
            if let Some(dir) = manifest.parent() {
                return Ok(dir.to_path_buf());
            }
        }
    }
    Err("the ruckig package was not found in cargo metadata".to_string())
}

fn main() {
    let root = match ruckig_root() {
        Ok(r) => r,
        Err(e) => panic!("chunkrt build: cannot locate the ruckig C++ sources: {e}"),
    };
    let sources = [
        "brake.cpp",
        "position_first_step1.cpp",
        "position_first_step2.cpp",
        "position_second_step1.cpp",
        "position_second_step2.cpp",
        "position_third_step1.cpp",
        "position_third_step2.cpp",
        "velocity_second_step1.cpp",
        "velocity_second_step2.cpp",
        "velocity_third_step1.cpp",
        "velocity_third_step2.cpp",
    ];
    let mut build = cc::Build::new();
    build
        .cpp(true)
        .std("c++17")
        .opt_level(2)
        .include(root.join("include"))
        .include("ffi")
        .define("ruckig", "chunkrt_ruckig_impl")
        .warnings(false)
        .file("ffi/chunkrt_ruckig.cpp");
    for s in sources {
        build.file(root.join("src/ruckig").join(s));
    }
    build.compile("chunkrt_ruckig");
    println!("cargo:rerun-if-changed=ffi");
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=CHUNKRT_RUCKIG_DIR");
}
