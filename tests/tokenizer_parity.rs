//! Token parity with openpi: chunkrt's SentencePiece reader and prompt builder against the ids
//! openpi's own `PaligemmaTokenizer` (openpi commit 15a9616, the `sentencepiece` package) gave
//! for the same prompts, states and lengths (`tests/data/tokenizer/`, made by
//! `scripts/fixtures/make_tokenizer_fixture.py` with a tiny model trained like PaliGemma's: BPE,
//! byte fallback, identity normalisation, digits split).

use chunkrt_policy::preprocess::{discretize_state, PromptTokenizer};
use chunkrt_policy::sentencepiece::SentencePiece;
use serde::Deserialize;

#[derive(Deserialize)]
struct Case {
    prompt: String,
    state: Option<Vec<f64>>,
    max_len: usize,
    ids: Vec<u32>,
    mask: Vec<bool>,
}

#[derive(Deserialize)]
struct Encode {
    text: String,
    ids: Vec<u32>,
}

#[derive(Deserialize)]
struct Fixture {
    vocab_size: usize,
    bos_id: u32,
    cases: Vec<Case>,
    encode: Vec<Encode>,
}

fn data() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/tokenizer")
}

fn fixture() -> Fixture {
    let text = std::fs::read_to_string(data().join("openpi_tokens.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

#[test]
fn sentencepiece_encodes_as_the_sentencepiece_package() {
    let f = fixture();
    let sp = SentencePiece::from_file(&data().join("paligemma_tiny.model")).unwrap();
    assert_eq!(sp.vocab_size(), f.vocab_size);
    assert_eq!(sp.bos_id(), Some(f.bos_id));
    let mut byte_fallbacks = 0;
    for e in &f.encode {
        let ids = sp.encode(&e.text);
        assert_eq!(ids, e.ids, "encode({:?})", e.text);
        byte_fallbacks += ids.iter().filter(|&&i| (4..260).contains(&i)).count();
    }
    // the fixture exercises byte fallback (non-ASCII text has no pieces in the tiny model)
    assert!(byte_fallbacks > 10, "{byte_fallbacks} byte pieces");
    eprintln!(
        "{} raw encodings equal, {byte_fallbacks} byte-fallback ids",
        f.encode.len()
    );
}

#[test]
fn prompts_and_states_tokenize_as_openpi() {
    let f = fixture();
    let tok = PromptTokenizer::from_sentencepiece(&data().join("paligemma_tiny.model")).unwrap();
    let (mut pi0, mut pi05, mut truncated) = (0, 0, 0);
    for c in &f.cases {
        let bins = c.state.as_ref().map(|s| {
            let s: Vec<f32> = s.iter().map(|&x| x as f32).collect();
            discretize_state(&s)
        });
        let (ids, mask, full) = tok
            .tokenize_counted(&c.prompt, bins.as_deref(), c.max_len)
            .unwrap();
        assert_eq!(
            ids, c.ids,
            "prompt {:?} state {:?} max_len {}",
            c.prompt, c.state, c.max_len
        );
        assert_eq!(mask, c.mask, "mask of {:?}", c.prompt);
        if bins.is_some() {
            pi05 += 1;
        } else {
            pi0 += 1;
        }
        truncated += usize::from(full > c.max_len);
    }
    eprintln!(
        "{pi0} pi0 and {pi05} pi0.5 prompts equal openpi's ids ({truncated} truncated to the limit)"
    );
    assert!(pi0 >= 10 && pi05 >= 10 && truncated >= 5);
}

/// The same model as a Hugging Face `tokenizer.json` (what LeRobot uses: transformers'
/// conversion of the SentencePiece model, made by `scripts/fixtures/make_lerobot_fixture.py`)
/// gives the same ids through chunkrt's `tokenizer.json` path.
#[test]
fn the_hugging_face_conversion_tokenizes_as_openpi() {
    let f = fixture();
    let tok = PromptTokenizer::from_file(&data().join("paligemma_tiny.tokenizer.json")).unwrap();
    assert_eq!(tok.id_bound(), f.vocab_size);
    for c in &f.cases {
        let bins = c.state.as_ref().map(|s| {
            let s: Vec<f32> = s.iter().map(|&x| x as f32).collect();
            discretize_state(&s)
        });
        let (ids, mask) = tok.tokenize(&c.prompt, bins.as_deref(), c.max_len).unwrap();
        assert_eq!(ids, c.ids, "prompt {:?} state {:?}", c.prompt, c.state);
        assert_eq!(mask, c.mask);
    }
    eprintln!("{} cases equal through tokenizer.json", f.cases.len());
}

/// LeRobot's pi0 prompt: the task as given with a newline, tokenised whole (its pre-processor
/// appends the newline, its tokenizer step adds BOS); openpi cleans the prompt and tokenises
/// the newline apart. The two agree on a clean prompt and differ on an underscored one.
#[test]
fn lerobot_pi0_prompts_keep_the_task_as_given() {
    use chunkrt_policy::preprocess::PromptStyle;
    let sp = SentencePiece::from_file(&data().join("paligemma_tiny.model")).unwrap();
    let tok = PromptTokenizer::from_sentencepiece(&data().join("paligemma_tiny.model")).unwrap();
    let styled = |p: &str, s| tok.tokenize_styled(p, None, 48, s).unwrap().0;
    let task = "put_the_cup on the plate";
    let mut want = vec![2];
    want.extend(sp.encode(&format!("{task}\n")));
    want.resize(48, 0);
    assert_eq!(styled(task, PromptStyle::LeRobot), want);
    assert_eq!(styled(&format!("{task}\n"), PromptStyle::LeRobot), want);
    assert_ne!(
        styled(task, PromptStyle::LeRobot),
        styled(task, PromptStyle::Openpi)
    );
    let clean = "pick up the red block";
    assert_eq!(
        styled(clean, PromptStyle::LeRobot),
        styled(clean, PromptStyle::Openpi)
    );
}
