//! Builds `chunkrt_ruckig`: an allocation-free C shim (`ffi/`) over the official ruckig C++
//! sources shipped by the `ruckig` crate (located with `cargo metadata --offline`).
//! Only the local (non-cloud) sources are compiled; the namespace is renamed so the symbols
//! never clash with the `ruckig` crate's own static library in binaries that link both.

use std::path::PathBuf;
use std::process::Command;

fn ruckig_root() -> Result<PathBuf, String> {
    if let Ok(dir) = std::env::var("CHUNKRT_RUCKIG_DIR") {
        return Ok(PathBuf::from(dir));
    }
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".to_string());
    let manifest_dir = std::env::var("CARGO_MANIFEST_DIR").map_err(|e| e.to_string())?;
    let out = Command::new(cargo)
        .args(["metadata", "--offline", "--format-version", "1"])
        .current_dir(&manifest_dir)
        .output()
        .map_err(|e| format!("cannot run cargo metadata: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "cargo metadata failed: {}",
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    // Find the `ruckig` package's manifest_path without a JSON dependency: packages are objects
    // with "name":"ruckig" followed (in the same object) by "manifest_path":"...".
    let mut rest: &str = &text;
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
