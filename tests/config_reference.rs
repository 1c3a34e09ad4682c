//! The configuration reference (`docs/config.md`) cannot drift from the configuration types:
//! every key the parser accepts is in the page, and every key in the page is one the parser
//! accepts. The keys are found from the parser itself: every section rejects unknown keys, and
//! its error lists the ones it expects, so a probe key in each table enumerates the fields, table
//! by table, down to the arrays of tables.

use std::collections::BTreeSet;

use chunkrt_controller::config::{Config, DEFAULT_TOML};

const PROBE: &str = "zz_probe_zz";

/// One step of a key path: a table's field, or the first element of an array of tables.
#[derive(Clone, Debug)]
enum Step {
    Field(String),
    Element,
}

fn key_name(path: &[Step]) -> String {
    let mut s = String::new();
    for step in path {
        match step {
            Step::Field(f) => {
                if !s.is_empty() {
                    s.push('.');
                }
                s.push_str(f);
            }
            Step::Element => s.push_str("[]"),
        }
    }
    s
}

/// The default configuration with a table (or an array of one table) created along `path` and
/// the probe key put into the last one. `as_array`: the last step makes an array of tables.
fn probed(path: &[Step], as_array: bool) -> String {
    let mut root: toml::Table = toml::from_str(DEFAULT_TOML).unwrap();
    let mut t = &mut root;
    let mut i = 0;
    while i < path.len() {
        let Step::Field(f) = &path[i] else {
            panic!("an element step must follow a field: {}", key_name(path));
        };
        let array =
            matches!(path.get(i + 1), Some(Step::Element)) || (i + 1 == path.len() && as_array);
        let entry = t
            .entry(f.clone())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        if array {
            let ok = entry
                .as_array()
                .is_some_and(|a| a.first().is_some_and(|v| v.is_table()));
            if !ok {
                *entry = toml::Value::Array(vec![toml::Value::Table(toml::Table::new())]);
            }
            t = entry.as_array_mut().unwrap()[0].as_table_mut().unwrap();
            i += if matches!(path.get(i + 1), Some(Step::Element)) {
                2
            } else {
                1
            };
        } else {
            if !entry.is_table() {
                *entry = toml::Value::Table(toml::Table::new());
            }
            t = entry.as_table_mut().unwrap();
            i += 1;
        }
    }
    t.insert(PROBE.into(), toml::Value::Integer(1));
    toml::to_string(&root).unwrap()
}

/// The fields the parser expects where the probe key sits, if it rejected the probe key as
/// unknown (None: the value is not a table of fields there).
fn expected(text: &str) -> Option<Vec<String>> {
    let err = match Config::parse(text, "probe") {
        Ok(_) => return None,
        Err(e) => e.to_string(),
    };
    let at = err.find(&format!("unknown field `{PROBE}`"))?;
    let rest = &err[at..];
    let rest = &rest[rest.find("expected")?..];
    let rest = rest.lines().next().unwrap_or("");
    let fields: Vec<String> = rest
        .split('`')
        .skip(1)
        .step_by(2)
        .map(String::from)
        .collect();
    Some(fields)
}

/// Every key under `path`, found by probing.
fn keys(path: Vec<Step>, out: &mut BTreeSet<String>, depth: usize) {
    assert!(depth < 8, "too deep at {}", key_name(&path));
    let fields = expected(&probed_path(&path)).unwrap_or_else(|| {
        panic!(
            "{}: the probe key was not rejected as unknown (a section without \
             deny_unknown_fields?)",
            key_name(&path)
        )
    });
    for f in fields {
        let mut p = path.clone();
        p.push(Step::Field(f.clone()));
        if expected(&probed(&p, false)).is_some() {
            keys(p, out, depth + 1);
        } else if expected(&probed(&p, true)).is_some() {
            p.push(Step::Element);
            keys(p, out, depth + 1);
        } else {
            out.insert(key_name(&p));
        }
    }
}

/// `probed` for a path that may end in an array element.
fn probed_path(path: &[Step]) -> String {
    match path.last() {
        Some(Step::Element) => probed(&path[..path.len() - 1], true),
        _ => probed(path, false),
    }
}

/// The keys the page documents: the first cell of its key tables, `` `section.key` ``.
fn page_keys() -> BTreeSet<String> {
    let page = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/config.md"))
        .expect("docs/config.md");
    page.lines()
        .filter_map(|l| l.strip_prefix("| `"))
        .filter_map(|l| l.split('`').next())
        .map(String::from)
        .collect()
}

#[test]
fn the_configuration_reference_lists_exactly_the_keys_the_parser_accepts() {
    let mut accepted = BTreeSet::new();
    keys(Vec::new(), &mut accepted, 0);
    let documented = page_keys();
    let missing: Vec<_> = accepted.difference(&documented).collect();
    let extra: Vec<_> = documented.difference(&accepted).collect();
    println!("{} keys accepted by the parser", accepted.len());
    assert!(
        missing.is_empty() && extra.is_empty(),
        "docs/config.md and the configuration types disagree:\n  accepted but not documented: \
         {missing:?}\n  documented but not accepted: {extra:?}"
    );
    assert!(accepted.len() > 50, "only {} keys found", accepted.len());
}
