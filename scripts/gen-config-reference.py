#!/usr/bin/env python3
"""Writes docs/config.md, the configuration reference, from the configuration types' sources.

    python3 scripts/gen-config-reference.py        # rewrites docs/config.md

Starts at `Config` (controller/src/config.rs) and follows each field's type through the structs of
the crates that own the sections (ipc, controller, openpi, policy): a struct becomes a section, a
`Vec<Struct>` an array of tables (`key[]`), anything else a key. Each key's row gives its type,
the value in the embedded default configuration (config/default.toml) or the serde default
function's body, and the field's doc comment. `tests/config_reference.rs` checks the page against
the parser itself, so a key added, removed or renamed without running this fails the suite.
"""
import pathlib
import re
import tomllib

ROOT = pathlib.Path(__file__).resolve().parent.parent
SOURCES = ["controller/src/config.rs", "ipc/src/config.rs", "ipc/src/config/ros2.rs", "openpi/src/layout.rs", "policy/src/config.rs"]
SECTION_TEXT = {
    "robot": "The robot: its namespace and joints (what every process of a robot shares).",
    "robot.joints[]": "One table per joint, in command order.",
    "control": "The control loop.",
    "cameras[]": "One table per camera.",
    "policy": "Where the chunks come from, and the policy's options.",
    "execution": "How chunks are executed: the strategy, interpolation, tracking, triggers.",
    "openpi": "The openpi protocol's request layout (`chunkrt serve`, `policy.source = \"remote\"`).",
    "serve": "`chunkrt serve`'s connection limits (its flags override).",
}


def structs():
    """name -> {"fields": [(name, type, doc, default_fn, skip)], "file": path}"""
    out = {}
    fns = {}
    for src in SOURCES:
        text = (ROOT / src).read_text()
        for m in re.finditer(r"fn (\w+)\(\) -> [^{]+\{\s*(.*?)\s*\}", text, re.S):
            body = " ".join(m.group(2).split())
            if len(body) < 60:
                fns[m.group(1)] = body
        for m in re.finditer(r"pub struct (\w+) \{(.*?)\n\}", text, re.S):
            fields = []
            doc, attrs = [], []
            open_attr = False  # inside an attribute rustfmt spread over lines
            for line in m.group(2).split("\n"):
                s = line.strip()
                if open_attr:
                    attrs[-1] += " " + s
                    open_attr = not s.endswith("]")
                elif s.startswith("///"):
                    doc.append(s[3:].strip())
                elif s.startswith("#["):
                    attrs.append(s)
                    open_attr = not s.endswith("]")
                elif s.startswith("pub "):
                    fm = re.match(r"pub (\w+): (.+),$", s)
                    if fm:
                        a = " ".join(attrs)
                        dm = re.search(r'default = "(\w+)"', a)
                        fields.append((fm.group(1), fm.group(2), " ".join(doc),
                                       dm.group(1) if dm else None, "skip" in a,
                                       "serde(default" in a))
                    doc, attrs = [], []
                elif s and not s.startswith("//"):
                    doc, attrs = [], []
            out[m.group(1)] = {"fields": fields, "file": src}
    return out, fns


def has_default(struct, field):
    return any(f[0] == field and f[3] is not None for f in struct["fields"]) or any(
        f[0] == field and f[5] for f in struct["fields"])


def inner(ty, wrapper):
    m = re.fullmatch(wrapper + r"<(.+)>", ty)
    return m.group(1) if m else None


def walk(all_structs, fns, name, prefix, defaults, rows):
    for field, ty, doc, default_fn, skip, _ in all_structs[name]["fields"]:
        if skip:
            continue
        key = f"{prefix}.{field}" if prefix else field
        base = inner(ty, "Option") or ty
        vec = inner(base, "Vec")
        if base in all_structs:
            rows.append(("section", key, doc))
            walk(all_structs, fns, base, key, (defaults or {}).get(field) or {}, rows)
        elif vec in all_structs:
            rows.append(("section", key + "[]", doc))
            d = (defaults or {}).get(field) or [{}]
            walk(all_structs, fns, vec, key + "[]", d[0] if d else {}, rows)
        else:
            value = None
            in_array = "[]" in prefix
            if isinstance(defaults, dict) and field in defaults and not in_array:
                value = "`" + repr_toml(defaults[field]) + "`"
            elif default_fn and default_fn in fns:
                value = "`" + fns[default_fn] + "`"
            elif ty.startswith("Option<"):
                value = "unset"
            elif default_fn is None and not has_default(all_structs[name], field):
                value = "required"
            rows.append(("key", key, ty, value, doc))


def repr_toml(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, list):
        return "[" + ", ".join(repr_toml(x) for x in v) + "]"
    return str(v)


def main():
    all_structs, fns = structs()
    defaults = tomllib.loads((ROOT / "config/default.toml").read_text())
    rows = []
    walk(all_structs, fns, "Config", "", defaults, rows)
    out = [
        "# Configuration reference",
        "",
        "Every key of a chunkrt configuration file, by section: its type, its value in the embedded default",
        "configuration (`config/default.toml`, what `chunkrt run` uses without `--config`) or its default when",
        "the file leaves it out, and what it means. Unknown keys are errors (a typo must not fall back to a",
        "default); every value is checked on load, and the error names the file, the key and what is allowed.",
        "Units are in the key's name (`_ms`, `_hz`, `_s`) or its description; joint quantities are rad (or m",
        "for a linear joint) per second, per second², per second³.",
        "",
        "`chunkrt run [--config FILE] [flags] --print-config` prints the effective configuration as TOML,",
        "each value marked `file`, `default` or `flag`, and exits; the printout is itself a valid file.",
        "",
        "Written by `python3 scripts/gen-config-reference.py` from the configuration types' sources;",
        "`tests/config_reference.rs` fails when this page and the parser disagree on the set of keys.",
        "",
    ]
    section = None
    for r in rows:
        if r[0] == "section":
            _, key, doc = r
            out += ["", f"## `[{key}]`" if not key.endswith("[]") else f"## `[[{key[:-2]}]]`", ""]
            text = SECTION_TEXT.get(key) or doc
            if text:
                out += [text, ""]
            out += ["| key | type | default | meaning |", "|---|---|---|---|"]
            section = key
            continue
        _, key, ty, value, doc = r
        if section is None:
            section = ""
        cell = (doc or "").replace("|", "\\|")
        if value is None:
            value = {"f64": "`0.0`", "bool": "`false`", "usize": "`0`", "u32": "`0`", "u64": "`0`",
                     "i32": "`0`", "String": '`""`'}.get(ty, "`[]`" if ty.startswith("Vec<") else
                                                     "the type's default (see meaning)")
        out.append(f"| `{key}` | `{ty}` | {value} | {cell} |")
    (ROOT / "docs/config.md").write_text("\n".join(out).rstrip() + "\n")
    print(f"docs/config.md: {sum(1 for r in rows if r[0] == 'key')} keys")


if __name__ == "__main__":
    main()
