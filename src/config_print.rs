//! `chunkrt run --print-config`: the effective configuration as TOML, each value with where it
//! came from: the file (or the embedded default), a serde default, or a command-line flag.

use anyhow::Context;
use chunkrt_controller::config::Config;
use toml::{Table, Value};

/// The sections in the order config/default.toml writes them.
const SECTIONS: [&str; 7] = [
    "robot",
    "control",
    "cameras",
    "policy",
    "execution",
    "openpi",
    "serve",
];

/// Where a value came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Origin {
    File,
    Default,
    Flag,
}

impl Origin {
    fn name(self) -> &'static str {
        match self {
            Origin::File => "file",
            Origin::Default => "default",
            Origin::Flag => "flag",
        }
    }
}

/// The effective configuration `effective` as TOML with a comment per value: `flag` where it
/// differs from `from_file` (the same configuration before the flags), else `file` where the
/// file's text (`file_text`) sets it, else `default`. `file_name` heads the output.
pub fn render(
    effective: &Config,
    from_file: &Config,
    file_text: &str,
    file_name: &str,
) -> anyhow::Result<String> {
    let eff = as_table(effective)?;
    let before = as_table(from_file)?;
    let file: Table = toml::from_str(file_text).with_context(|| format!("parse {file_name}"))?;
    let mut out = format!(
        "# the effective configuration: {file_name}\n# each value: file (set there), default \
         (not set in the file), flag (set on the command line)\n"
    );
    let mut counts = [0usize; 3];
    write_table(&mut out, &[], &eff, Some(&before), Some(&file), &mut counts);
    out.push_str(&format!(
        "\n# {} from the file, {} defaults, {} from flags\n",
        counts[0], counts[1], counts[2]
    ));
    Ok(out)
}

fn as_table(cfg: &Config) -> anyhow::Result<Table> {
    match Value::try_from(cfg).context("serialize the configuration")? {
        Value::Table(t) => Ok(t),
        _ => anyhow::bail!("the configuration did not serialize to a table"),
    }
}

/// Whether a value is written on the table's own lines (not a table or an array of tables).
fn is_leaf(v: &Value) -> bool {
    match v {
        Value::Table(_) => false,
        Value::Array(a) => !(a.first().is_some_and(|x| x.is_table())),
        _ => true,
    }
}

fn write_table(
    out: &mut String,
    path: &[String],
    eff: &Table,
    before: Option<&Table>,
    file: Option<&Table>,
    counts: &mut [usize; 3],
) {
    for (k, v) in eff.iter().filter(|(_, v)| is_leaf(v)) {
        let origin = if before.and_then(|b| b.get(k)) != Some(v) {
            Origin::Flag
        } else if file.is_some_and(|f| f.contains_key(k)) {
            Origin::File
        } else {
            Origin::Default
        };
        counts[origin as usize] += 1;
        let line = format!("{} = {v}", key(k));
        out.push_str(&format!("{line:<48} # {}\n", origin.name()));
    }
    // the file's order at the top (robot first), the rest as they come
    let mut tables: Vec<(&String, &Value)> = eff.iter().filter(|(_, v)| !is_leaf(v)).collect();
    if path.is_empty() {
        tables.sort_by_key(|(k, _)| {
            SECTIONS
                .iter()
                .position(|s| s == k)
                .unwrap_or(SECTIONS.len())
        });
    }
    for (k, v) in tables {
        let mut p = path.to_vec();
        p.push(key(k));
        match v {
            Value::Table(t) => {
                out.push_str(&format!("\n[{}]\n", p.join(".")));
                write_table(
                    out,
                    &p,
                    t,
                    before.and_then(|b| b.get(k)).and_then(Value::as_table),
                    file.and_then(|f| f.get(k)).and_then(Value::as_table),
                    counts,
                );
            }
            Value::Array(items) => {
                let b = before.and_then(|b| b.get(k)).and_then(Value::as_array);
                let f = file.and_then(|f| f.get(k)).and_then(Value::as_array);
                for (i, item) in items.iter().enumerate() {
                    let Some(t) = item.as_table() else { continue };
                    out.push_str(&format!("\n[[{}]]\n", p.join(".")));
                    write_table(
                        out,
                        &p,
                        t,
                        b.and_then(|b| b.get(i)).and_then(Value::as_table),
                        f.and_then(|f| f.get(i)).and_then(Value::as_table),
                        counts,
                    );
                }
            }
            _ => {}
        }
    }
}

/// A key as TOML writes it: bare where it can be.
fn key(k: &str) -> String {
    if !k.is_empty()
        && k.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    {
        k.to_string()
    } else {
        Value::String(k.to_string()).to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use chunkrt_controller::config::{PolicySource, DEFAULT_TOML};

    #[test]
    fn the_printout_reads_back_as_the_effective_configuration_and_names_each_origin() {
        let from_file = Config::embedded_default();
        let mut eff = from_file.clone();
        eff.policy.source = PolicySource::Scripted;
        eff.robot.namespace = "printed".into();
        let text = render(&eff, &from_file, DEFAULT_TOML, "default.toml").unwrap();
        // valid TOML that parses to the same configuration
        let mut back = Config::parse(&text, "printout").unwrap();
        back.source = eff.source.clone();
        assert_eq!(back, eff, "{text}");
        let origin = |line_start: &str| {
            let line = text
                .lines()
                .find(|l| l.starts_with(line_start))
                .unwrap_or_else(|| panic!("no {line_start} in\n{text}"));
            line.rsplit("# ").next().unwrap().to_string()
        };
        assert_eq!(origin("source = "), "flag");
        assert_eq!(origin("namespace = "), "flag");
        assert_eq!(origin("rate_hz = "), "file");
        assert_eq!(origin("robot_clock_timeout_ms = "), "default");
        assert!(text.find("[robot]").unwrap() < text.find("[control]").unwrap());
    }
}
