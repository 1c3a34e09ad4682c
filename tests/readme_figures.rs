//! Every figure the README quotes is a figure of BENCHMARKS.md or docs/status.md, with the same
//! value: the README's figures cannot drift from the pages that give their source again.
//!
//! The README marks what is checked: the lines between `<!-- figures -->` and `<!-- /figures
//! -->` (the demo's table and the Status section). A figure there is a number with a unit (`×`,
//! `x`, `ms`, `µs`, `s`, `%`, `rad`, `M`, `MB`, `GB`, `min`, `Hz`, `kHz`), a decimal or
//! scientific number (`0.99989`, `7.2e-7`), or a list of numbers joined by ` / ` or `–`
//! (`6.63 / 17.3 / 116.8`). It holds when BENCHMARKS.md or docs/status.md has the same number
//! with the same unit (a list or range there gives its unit to each of its numbers: `14.9 / 41.4
//! µs` holds `41.4 µs`), the same number for a figure without a unit, and the same list for a
//! list without a unit. Numbers are compared as written: `1.8×` does not match `1.79×`.
//!
//! Reads three files; no build of the project's crates, no processes.

use std::collections::HashSet;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");
const START: &str = "<!-- figures -->";
const END: &str = "<!-- /figures -->";

/// A figure as written: its numbers (one, or a list), its unit, and the line it is on.
#[derive(Debug, Clone)]
struct Figure {
    values: Vec<String>,
    unit: Option<&'static str>,
    line: usize,
    text: String,
}

const UNITS: &[(&str, &str)] = &[
    ("minutes", "min"),
    ("µs", "µs"),
    ("us", "µs"),
    ("ms", "ms"),
    ("min", "min"),
    ("rad", "rad"),
    ("kHz", "kHz"),
    ("Hz", "Hz"),
    ("GB", "GB"),
    ("MB", "MB"),
    ("M", "M"),
    ("s", "s"),
    ("%", "%"),
    ("×", "×"),
];

/// Markdown emphasis and non-breaking spaces out, so that `**1.79×**` reads as `1.79×`.
fn clean(line: &str) -> String {
    line.replace("**", "").replace(['\u{a0}', '\u{202f}'], " ")
}

/// The number starting at `i` (digits, a decimal part, an exponent), as written, and where it
/// ends; None when `i` does not start one (a digit inside a word: `p99`, `pi05`, `π0`).
fn number(c: &[char], i: usize) -> Option<(String, usize)> {
    if !c[i].is_ascii_digit() {
        return None;
    }
    if i > 0 && (c[i - 1].is_alphanumeric() || matches!(c[i - 1], '.' | '_' | '-' | '/' | ',')) {
        return None;
    }
    let mut j = i;
    while j < c.len() && c[j].is_ascii_digit() {
        j += 1;
    }
    if j + 1 < c.len() && c[j] == '.' && c[j + 1].is_ascii_digit() {
        j += 1;
        while j < c.len() && c[j].is_ascii_digit() {
            j += 1;
        }
    }
    if j + 1 < c.len() && c[j] == 'e' {
        let k = if c[j + 1] == '-' { j + 2 } else { j + 1 };
        if k < c.len() && c[k].is_ascii_digit() {
            j = k;
            while j < c.len() && c[j].is_ascii_digit() {
                j += 1;
            }
        }
    }
    Some((c[i..j].iter().collect(), j))
}

/// The unit right after a number (one space allowed; `x` only when attached: `10.7x`).
fn unit(c: &[char], j: usize) -> Option<(&'static str, usize)> {
    let at_word_end = |k: usize| k >= c.len() || !c[k].is_alphanumeric();
    if j < c.len() && c[j] == 'x' && at_word_end(j + 1) {
        return Some(("×", j + 1));
    }
    let start = if j < c.len() && c[j] == ' ' { j + 1 } else { j };
    for (written, unit) in UNITS {
        let w: Vec<char> = written.chars().collect();
        let end = start + w.len();
        if end <= c.len() && c[start..end] == w[..] {
            // a letter unit ends its word; `×` and `%` stand alone (`64×64` is a size)
            let ok = match *unit {
                "×" => end >= c.len() || !c[end].is_ascii_digit(),
                "%" => true,
                _ => at_word_end(end),
            };
            if ok {
                return Some((unit, end));
            }
        }
    }
    None
}

/// Every figure of `text` (line numbers from `first_line`).
fn figures(text: &str, first_line: usize) -> Vec<Figure> {
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let c: Vec<char> = clean(line).chars().collect();
        let mut i = 0;
        while i < c.len() {
            let Some((first, mut j)) = number(&c, i) else {
                i += 1;
                continue;
            };
            let mut values = vec![first];
            // a list: `a / b / c` or a range `a–b`
            loop {
                let mut k = j;
                while k < c.len() && c[k] == ' ' {
                    k += 1;
                }
                if k < c.len() && (c[k] == '/' || c[k] == '–') {
                    let mut m = k + 1;
                    while m < c.len() && c[m] == ' ' {
                        m += 1;
                    }
                    if m < c.len() {
                        if let Some((v, e)) = number(&c, m) {
                            values.push(v);
                            j = e;
                            continue;
                        }
                    }
                }
                break;
            }
            let u = unit(&c, j);
            let end = u.map_or(j, |(_, e)| e);
            let figure = u.is_some()
                || values.len() > 1
                || values.iter().any(|v| v.contains('.') || v.contains('e'));
            if figure {
                out.push(Figure {
                    values,
                    unit: u.map(|(u, _)| u),
                    line: first_line + n,
                    text: c[i..end].iter().collect(),
                });
            }
            i = end.max(i + 1);
        }
    }
    out
}

/// What the source pages hold: (number, unit) pairs, the numbers, and the unitless lists.
struct Sources {
    with_unit: HashSet<(String, &'static str)>,
    numbers: HashSet<String>,
    lists: HashSet<String>,
}

impl Sources {
    fn of(texts: &[&str]) -> Sources {
        let mut s = Sources {
            with_unit: HashSet::new(),
            numbers: HashSet::new(),
            lists: HashSet::new(),
        };
        for text in texts {
            for f in figures(text, 1) {
                for v in &f.values {
                    s.numbers.insert(v.clone());
                    if let Some(u) = f.unit {
                        s.with_unit.insert((v.clone(), u));
                    }
                }
                if f.values.len() > 1 {
                    s.lists.insert(f.values.join("/"));
                }
            }
        }
        s
    }

    /// Whether the sources hold `f` with the same value.
    fn holds(&self, f: &Figure) -> bool {
        match (f.unit, f.values.len()) {
            (Some(u), _) => f
                .values
                .iter()
                .all(|v| self.with_unit.contains(&(v.clone(), u))),
            (None, 1) => self.numbers.contains(&f.values[0]),
            (None, _) => self.lists.contains(&f.values.join("/")),
        }
    }
}

/// The README's marked regions, each with its first line number.
fn marked(readme: &str) -> Vec<(usize, String)> {
    let mut regions = Vec::new();
    let mut current: Option<(usize, String)> = None;
    for (n, line) in readme.lines().enumerate() {
        if line.trim() == START {
            assert!(
                current.is_none(),
                "README line {}: {START} inside another",
                n + 1
            );
            current = Some((n + 2, String::new()));
        } else if line.trim() == END {
            regions.push(current.take().expect("an end marker without its start"));
        } else if let Some((_, text)) = current.as_mut() {
            text.push_str(line);
            text.push('\n');
        }
    }
    assert!(current.is_none(), "README: {START} is not closed");
    regions
}

/// The README's marked figures that the sources do not hold.
fn unheld(readme: &str, sources: &Sources) -> (Vec<Figure>, Vec<Figure>) {
    let all: Vec<Figure> = marked(readme)
        .iter()
        .flat_map(|(first, text)| figures(text, *first))
        .collect();
    let missing = all.iter().filter(|f| !sources.holds(f)).cloned().collect();
    (all, missing)
}

fn read(path: &str) -> String {
    std::fs::read_to_string(format!("{ROOT}/{path}")).unwrap_or_else(|e| panic!("{path}: {e}"))
}

fn sources() -> Sources {
    Sources::of(&[&read("BENCHMARKS.md"), &read("docs/status.md")])
}

fn describe(f: &Figure) -> String {
    format!("README line {}: {:?}", f.line, f.text)
}

#[test]
fn every_figure_the_readme_quotes_is_in_the_benchmarks_or_the_status_page() {
    let readme = read("README.md");
    let (all, missing) = unheld(&readme, &sources());
    println!(
        "{} figures checked in the README's marked lines:",
        all.len()
    );
    for f in &all {
        println!("  {}", describe(f));
    }
    // the demo's table and the Status section are marked: far more than this many figures
    assert!(
        all.len() >= 25,
        "only {} figures between {START} and {END}: were the markers moved?",
        all.len()
    );
    assert!(
        missing.is_empty(),
        "figures of the README that neither BENCHMARKS.md nor docs/status.md holds with the \
         same value (fix the README or the page it comes from):\n{}",
        missing.iter().map(describe).collect::<Vec<_>>().join("\n")
    );
}

/// The check itself can fail: the README with one figure changed (the first of each kind of
/// figure, one at a time) is caught.
#[test]
fn a_changed_figure_is_caught() {
    let readme = read("README.md");
    let sources = sources();
    let (all, _) = unheld(&readme, &sources);
    let mut tried = 0;
    for kind in [Some("×"), Some("ms"), Some("µs"), None] {
        let Some(f) = all
            .iter()
            .find(|f| f.unit == kind && f.values[0].contains('.'))
        else {
            continue;
        };
        // the same figure off in its last digit (1.79× → 1.71×, say), to a value the pages do
        // not hold by chance for another figure
        let v = &f.values[0];
        let last = v.chars().last().unwrap().to_digit(10).unwrap();
        let wrong = (1..10)
            .map(|d| format!("{}{}", &v[..v.len() - 1], (last + d) % 10))
            .find(|w| {
                let mut g = f.clone();
                g.values[0] = w.clone();
                !sources.holds(&g)
            })
            .expect("a wrong value the pages do not hold");
        let line = readme.lines().nth(f.line - 1).unwrap();
        let changed_line = line.replacen(v.as_str(), &wrong, 1);
        let changed = readme.replacen(line, &changed_line, 1);
        let (_, missing) = unheld(&changed, &sources);
        let caught = missing.iter().any(|m| m.line == f.line);
        println!("{} → {wrong}: caught {caught}", describe(f));
        assert!(caught, "{} changed to {wrong} was not caught", describe(f));
        tried += 1;
    }
    assert!(tried >= 3, "only {tried} kinds of figure found to change");
}

#[test]
fn figures_are_read_as_written() {
    let f = figures(
        "p50 / p99 **14.9 / 41.4 µs**, 1.79× (2.65x), π0.5 at 7.2e-7, 64×64, 0.0017–0.0024 rad, \
         tick 6.63 / 17.3 / 116.8, pi05 2 cores, 0.99989",
        1,
    );
    let got: Vec<(String, Option<&str>)> = f.iter().map(|f| (f.values.join("/"), f.unit)).collect();
    let want: Vec<(String, Option<&str>)> = vec![
        ("14.9/41.4".into(), Some("µs")),
        ("1.79".into(), Some("×")),
        ("2.65".into(), Some("×")),
        ("7.2e-7".into(), None),
        ("0.0017/0.0024".into(), Some("rad")),
        ("6.63/17.3/116.8".into(), None),
        ("0.99989".into(), None),
    ];
    assert_eq!(got, want);
    let s = Sources::of(&["lateness 14.9 / 41.4 µs; 1.79× in the same run"]);
    let holds = |t: &str| figures(t, 1).iter().all(|f| s.holds(f));
    assert!(holds("41.4 µs"));
    assert!(holds("**1.79×**"));
    assert!(!holds("1.8×"));
    assert!(!holds("41.4 ms"));
    assert!(!holds("41 µs"));
}
