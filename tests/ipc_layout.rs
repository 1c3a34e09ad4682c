//! The message contract is identical in Rust, C (`ipc/include/chunkrt_ipc.h`) and Python
//! (`ipc/python/chunkrt_ipc.py`): every struct's size, alignment and field offsets, every
//! constant, every iceoryx2 type name and the services' quality of service.
//!
//! The C side is a program generated here, compiled with the system C compiler (`$CC`, else
//! `cc`) and run; the Python side is `python3 chunkrt_ipc.py --layouts`. A missing compiler or
//! interpreter is reported loudly, and fails the test when `CI` is set.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use chunkrt_ipc::messages::layouts;
use chunkrt_ipc::services;
use chunkrt_ipc::*;
use iceoryx2::service::port_factory::PortFactory;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn in_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| !v.is_empty() && v != "0" && v != "false")
}

/// Missing tool: fail in CI, shout otherwise.
fn missing(what: &str, why: &str) {
    let msg = format!(
        "\n!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n\
         !!! ipc_layout: {what} is not available ({why}).\n\
         !!! The {what} side of the IPC contract was NOT checked.\n\
         !!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n"
    );
    if in_ci() {
        panic!("{msg}(CI is set: this is a failure)");
    }
    eprintln!("{msg}");
}

/// Every integer constant of the contract by its Rust name.
fn rust_constants() -> BTreeMap<String, u64> {
    let mut c: BTreeMap<String, u64> = [
        ("MAX_DOF", MAX_DOF as u64),
        ("MAX_CHUNK_HORIZON", MAX_CHUNK_HORIZON as u64),
        ("CONTRACT_VERSION", CONTRACT_VERSION as u64),
        ("BUFFER_SIZE", services::BUFFER_SIZE as u64),
        ("CAMERA_BUFFER_SIZE", services::CAMERA_BUFFER_SIZE as u64),
        ("HISTORY_SIZE", services::HISTORY_SIZE as u64),
        ("MAX_NODES", services::MAX_NODES as u64),
        ("MAX_SUBSCRIBERS", services::MAX_SUBSCRIBERS as u64),
        ("MAX_PUBLISHERS", services::MAX_PUBLISHERS as u64),
        // Literals in services.rs (checked against a live service below where iceoryx2 exposes
        // them).
        ("SUBSCRIBER_MAX_BORROWED_SAMPLES", 2),
        ("PUBLISHER_MAX_LOANED_SAMPLES", 2),
        ("ENABLE_SAFE_OVERFLOW", 1),
        ("ENCODING_RGB8", ENCODING_RGB8 as u64),
        ("ENCODING_BGR8", ENCODING_BGR8 as u64),
        ("ENCODING_MONO8", ENCODING_MONO8 as u64),
        ("JOINT_STATUS_HOLDING", JOINT_STATUS_HOLDING as u64),
        (
            "JOINT_STATUS_COMMAND_EXPIRED",
            JOINT_STATUS_COMMAND_EXPIRED as u64,
        ),
        (
            "JOINT_STATUS_COMMAND_TIMEOUT",
            JOINT_STATUS_COMMAND_TIMEOUT as u64,
        ),
        (
            "JOINT_STATUS_COMMAND_REJECTED",
            JOINT_STATUS_COMMAND_REJECTED as u64,
        ),
        (
            "JOINT_STATUS_LIMIT_CLAMPED",
            JOINT_STATUS_LIMIT_CLAMPED as u64,
        ),
        (
            "JOINT_STATUS_SESSION_REPORTED",
            JOINT_STATUS_SESSION_REPORTED as u64,
        ),
        ("JOINT_STATUS_ROBOT_ERROR", JOINT_STATUS_ROBOT_ERROR as u64),
        ("JOINT_STATUS_AT_REST", JOINT_STATUS_AT_REST as u64),
        (
            "JOINT_STATUS_NOT_FOLLOWING",
            JOINT_STATUS_NOT_FOLLOWING as u64,
        ),
        ("JOINT_STATUS_COMMAND_FAR", JOINT_STATUS_COMMAND_FAR as u64),
        ("COMMAND_MODE_POSITION", COMMAND_MODE_POSITION as u64),
        ("COMMAND_MODE_HOLD", COMMAND_MODE_HOLD as u64),
        (
            "CONTROLLER_STATE_STARTING",
            CONTROLLER_STATE_STARTING as u64,
        ),
        ("CONTROLLER_STATE_HOLD", CONTROLLER_STATE_HOLD as u64),
        ("CONTROLLER_STATE_RUNNING", CONTROLLER_STATE_RUNNING as u64),
        ("CONTROLLER_STATE_FAULT", CONTROLLER_STATE_FAULT as u64),
        ("CONTROLLER_STATE_STOPPED", CONTROLLER_STATE_STOPPED as u64),
        (
            "CONTROLLER_STATE_NOT_FOLLOWED",
            CONTROLLER_STATE_NOT_FOLLOWED as u64,
        ),
        ("REJECT_REASON_COUNT", REJECT_REASON_COUNT as u64),
        ("STATE_REASON_NONE", STATE_REASON_NONE as u64),
        ("STATE_REASON_INPUTS_GOOD", STATE_REASON_INPUTS_GOOD as u64),
        (
            "STATE_REASON_STALE_JOINT_STATE",
            STATE_REASON_STALE_JOINT_STATE as u64,
        ),
        ("STATE_REASON_NO_CHUNK", STATE_REASON_NO_CHUNK as u64),
        (
            "STATE_REASON_STALE_CAMERA",
            STATE_REASON_STALE_CAMERA as u64,
        ),
        (
            "STATE_REASON_CHUNK_EXPIRED",
            STATE_REASON_CHUNK_EXPIRED as u64,
        ),
        (
            "STATE_REASON_NON_FINITE_ACTION",
            STATE_REASON_NON_FINITE_ACTION as u64,
        ),
        ("STATE_REASON_BAD_CHUNK", STATE_REASON_BAD_CHUNK as u64),
        ("STATE_REASON_OVERRUNS", STATE_REASON_OVERRUNS as u64),
        (
            "STATE_REASON_HOLD_TIMEOUT",
            STATE_REASON_HOLD_TIMEOUT as u64,
        ),
        (
            "STATE_REASON_BAD_JOINT_STATE",
            STATE_REASON_BAD_JOINT_STATE as u64,
        ),
        (
            "STATE_REASON_GENERATOR_ERROR",
            STATE_REASON_GENERATOR_ERROR as u64,
        ),
        ("STATE_REASON_REARM", STATE_REASON_REARM as u64),
        (
            "STATE_REASON_INFERENCE_ERROR",
            STATE_REASON_INFERENCE_ERROR as u64,
        ),
        ("STATE_REASON_NOT_OBEYED", STATE_REASON_NOT_OBEYED as u64),
        (
            "STATE_REASON_ROBOT_NOT_FOLLOWING",
            STATE_REASON_ROBOT_NOT_FOLLOWING as u64,
        ),
        ("REARM_NONE", REARM_NONE as u64),
        ("REARM_ACCEPTED", REARM_ACCEPTED as u64),
        (
            "REARM_REFUSED_NOT_IN_FAULT",
            REARM_REFUSED_NOT_IN_FAULT as u64,
        ),
        ("REARM_REFUSED_INPUTS", REARM_REFUSED_INPUTS as u64),
        ("REARM_MAX_AGE_NS", REARM_MAX_AGE_NS),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    for r in RejectReason::ALL {
        c.insert(
            format!("REJECT_{}", r.name().to_ascii_uppercase()),
            r.code() as u64,
        );
    }
    c
}

/// Rust type names, read back from live services (what iceoryx2 actually compares).
fn rust_type_names() -> BTreeMap<String, String> {
    let node = services::node("ipc-layout-test").expect("node");
    let ns = format!("chunkrt/test-{}-layout", std::process::id());
    let mut out = BTreeMap::new();
    let js = services::joint_state_service(&node, &format!("{ns}/joint_state")).unwrap();
    let jc = services::joint_command_service(&node, &format!("{ns}/joint_command")).unwrap();
    let st = services::status_service(&node, &format!("{ns}/status")).unwrap();
    let ra = services::rearm_service(&node, &format!("{ns}/rearm")).unwrap();
    let ch = services::chunk_service(&node, &format!("{ns}/chunks")).unwrap();
    let cam = services::camera_service(&node, &format!("{ns}/camera/c")).unwrap();
    for (k, d) in [
        (
            "JointState",
            js.static_config().message_type_details().payload,
        ),
        (
            "JointCommand",
            jc.static_config().message_type_details().payload,
        ),
        (
            "ControllerStatus",
            st.static_config().message_type_details().payload,
        ),
        (
            "RearmRequest",
            ra.static_config().message_type_details().payload,
        ),
        (
            "ActionChunkMsg",
            ch.static_config().message_type_details().payload,
        ),
        (
            "CameraFrameHeader",
            cam.static_config().message_type_details().user_header,
        ),
    ] {
        out.insert(k.to_string(), d.type_name().to_string());
    }
    assert_eq!(
        cam.static_config()
            .message_type_details()
            .payload
            .type_name()
            .to_string(),
        "u8",
        "camera pixel type"
    );
    // The QoS numbers the mirrors repeat, as the live services have them.
    for cfg in [js.static_config(), cam.static_config()] {
        assert_eq!(cfg.history_size(), services::HISTORY_SIZE);
        assert_eq!(cfg.max_nodes(), services::MAX_NODES);
        assert_eq!(cfg.max_publishers(), services::MAX_PUBLISHERS);
        assert_eq!(cfg.max_subscribers(), services::MAX_SUBSCRIBERS);
        assert_eq!(cfg.subscriber_max_borrowed_samples(), 2);
        assert!(cfg.has_safe_overflow());
    }
    assert_eq!(
        js.static_config().subscriber_max_buffer_size(),
        services::BUFFER_SIZE
    );
    assert_eq!(
        cam.static_config().subscriber_max_buffer_size(),
        services::CAMERA_BUFFER_SIZE
    );
    out
}

type Layout = (usize, Vec<(String, usize)>);

fn rust_layouts() -> BTreeMap<String, Layout> {
    layouts()
        .into_iter()
        .map(|(name, (size, fields))| {
            (
                name.to_string(),
                (
                    size,
                    fields
                        .into_iter()
                        .map(|(f, o)| (f.to_string(), o))
                        .collect(),
                ),
            )
        })
        .collect()
}

/// Size of every field, `Struct.field` → bytes: the contract has no padding, so a field spans
/// from its offset to the next field's (or the struct's end).
fn field_sizes(layouts: &BTreeMap<String, Layout>) -> BTreeMap<String, usize> {
    let mut out = BTreeMap::new();
    for (name, (size, fields)) in layouts {
        for (i, (f, off)) in fields.iter().enumerate() {
            let end = fields.get(i + 1).map(|x| x.1).unwrap_or(*size);
            out.insert(format!("{name}.{f}"), end - off);
        }
    }
    out
}

fn compare_layouts(lang: &str, rust: &BTreeMap<String, Layout>, other: &BTreeMap<String, Layout>) {
    assert_eq!(
        rust.keys().collect::<Vec<_>>(),
        other.keys().collect::<Vec<_>>(),
        "{lang}: struct names differ"
    );
    for (name, (size, fields)) in rust {
        let (osize, ofields) = &other[name];
        assert_eq!(size, osize, "{lang}: sizeof({name})");
        assert_eq!(fields, ofields, "{lang}: field offsets of {name}");
    }
}

fn c_program(layouts: &BTreeMap<String, Layout>, constants: &BTreeMap<String, u64>) -> String {
    let mut s = String::from(
        "#include <stddef.h>\n#include <stdio.h>\n#include \"chunkrt_ipc.h\"\nint main(void) {\n",
    );
    for (name, (_, fields)) in layouts {
        s += &format!(
            "  printf(\"size {name} %zu\\n\", sizeof({name}));\n  printf(\"align {name} %zu\\n\", _Alignof({name}));\n"
        );
        for (f, _) in fields {
            s += &format!(
                "  printf(\"field {name} {f} %zu %zu\\n\", offsetof({name}, {f}), sizeof((({name} *)0)->{f}));\n"
            );
        }
    }
    for k in constants.keys() {
        s += &format!("  printf(\"const {k} %llu\\n\", (unsigned long long)(CHUNKRT_{k}));\n");
    }
    for (k, macro_) in [
        ("CameraFrameHeader", "CAMERA_FRAME_HEADER"),
        ("JointState", "JOINT_STATE"),
        ("JointCommand", "JOINT_COMMAND"),
        ("ControllerStatus", "CONTROLLER_STATUS"),
        ("RearmRequest", "REARM_REQUEST"),
        ("ActionChunkMsg", "ACTION_CHUNK_MSG"),
    ] {
        s += &format!("  printf(\"type_name {k} %s\\n\", CHUNKRT_TYPE_NAME_{macro_});\n");
    }
    s += "  printf(\"type_name pixel %s\\n\", CHUNKRT_TYPE_NAME_PIXEL);\n  return 0;\n}\n";
    s
}

#[test]
fn ipc_layout_c_header_matches_rust() {
    let rust = rust_layouts();
    let consts = rust_constants();
    let names = rust_type_names();
    let dir = std::env::temp_dir().join(format!("chunkrt-ipc-layout-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let src = dir.join("layout.c");
    let exe = dir.join("layout");
    std::fs::write(&src, c_program(&rust, &consts)).unwrap();
    let cc = std::env::var("CC").unwrap_or_else(|_| "cc".to_string());
    let include = root().join("ipc/include");
    let compiled = Command::new(&cc)
        .args(["-std=c11", "-Wall", "-Werror", "-o"])
        .arg(&exe)
        .arg(&src)
        .arg("-I")
        .arg(&include)
        .output();
    let compiled = match compiled {
        Ok(o) => o,
        Err(e) => return missing("the C compiler", &format!("running '{cc}': {e}")),
    };
    assert!(
        compiled.status.success(),
        "the C header does not compile:\n{}",
        String::from_utf8_lossy(&compiled.stderr)
    );
    let out = Command::new(&exe).output().expect("run the layout program");
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    let _ = std::fs::remove_dir_all(&dir);

    let mut c_layouts: BTreeMap<String, Layout> = BTreeMap::new();
    let mut c_consts = BTreeMap::new();
    let mut c_names = BTreeMap::new();
    let mut c_sizes = BTreeMap::new();
    for line in text.lines() {
        let parts: Vec<&str> = line.split_whitespace().collect();
        match parts.as_slice() {
            ["size", name, v] => {
                c_layouts.entry(name.to_string()).or_default().0 = v.parse().unwrap()
            }
            ["align", name, v] => assert_eq!(v.parse::<usize>().unwrap(), 8, "C alignof({name})"),
            ["field", name, f, v, size] => {
                c_layouts
                    .entry(name.to_string())
                    .or_default()
                    .1
                    .push((f.to_string(), v.parse().unwrap()));
                c_sizes.insert(format!("{name}.{f}"), size.parse::<usize>().unwrap());
            }
            ["const", k, v] => {
                c_consts.insert(k.to_string(), v.parse::<u64>().unwrap());
            }
            ["type_name", k, v] => {
                c_names.insert(k.to_string(), v.to_string());
            }
            _ => panic!("unexpected output line {line:?}"),
        }
    }
    compare_layouts("C", &rust, &c_layouts);
    assert_eq!(field_sizes(&rust), c_sizes, "C field sizes");
    assert_eq!(consts, c_consts, "C constants");
    assert_eq!(c_names.remove("pixel").as_deref(), Some("u8"));
    assert_eq!(names, c_names, "C type names");
    eprintln!(
        "C header: {} structs, {} fields, {} constants identical to Rust",
        rust.len(),
        rust.values().map(|l| l.1.len()).sum::<usize>(),
        consts.len()
    );
}

fn python_layouts(mirror: &Path) -> Option<serde_json::Value> {
    let out = match Command::new("python3")
        .arg(mirror)
        .arg("--layouts")
        .output()
    {
        Ok(o) => o,
        Err(e) => {
            missing("python3", &e.to_string());
            return None;
        }
    };
    assert!(
        out.status.success(),
        "python3 {} --layouts failed:\n{}",
        mirror.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    Some(serde_json::from_slice(&out.stdout).expect("JSON from the Python mirror"))
}

#[test]
fn ipc_layout_python_mirror_matches_rust() {
    let rust = rust_layouts();
    let consts = rust_constants();
    let names = rust_type_names();
    let Some(v) = python_layouts(&root().join("ipc/python/chunkrt_ipc.py")) else {
        return;
    };
    let mut py: BTreeMap<String, Layout> = BTreeMap::new();
    let mut py_names = BTreeMap::new();
    let mut py_sizes = BTreeMap::new();
    let obj = v["layouts"].as_object().expect("layouts object");
    for (name, l) in obj {
        assert_eq!(l["align"].as_u64(), Some(8), "Python alignment of {name}");
        let fields = l["fields"]
            .as_array()
            .expect("fields")
            .iter()
            .map(|f| {
                let field = f[0].as_str().expect("field name").to_string();
                py_sizes.insert(
                    format!("{name}.{field}"),
                    f[2].as_u64().expect("field size") as usize,
                );
                (field, f[1].as_u64().expect("offset") as usize)
            })
            .collect();
        py.insert(
            name.clone(),
            (l["size"].as_u64().expect("size") as usize, fields),
        );
        py_names.insert(
            name.clone(),
            l["type_name"].as_str().expect("type_name").to_string(),
        );
    }
    compare_layouts("Python", &rust, &py);
    assert_eq!(field_sizes(&rust), py_sizes, "Python field sizes");
    let py_consts: BTreeMap<String, u64> = v["constants"]
        .as_object()
        .expect("constants")
        .iter()
        .map(|(k, v)| (k.clone(), v.as_u64().expect("integer constant")))
        .collect();
    assert_eq!(consts, py_consts, "Python constants");
    assert_eq!(names, py_names, "Python type names");
    eprintln!(
        "Python mirror: {} structs, {} constants identical to Rust",
        py.len(),
        py_consts.len()
    );
}
