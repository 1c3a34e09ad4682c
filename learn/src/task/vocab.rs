//! The task's `tokenizer.json`: a word-level vocabulary (the `tokenizers` crate's `WordLevel`
//! model with its `Whitespace` pre-tokenizer) covering the π0.5 prompt of the reach task —
//! `Task: reach the red target, State: 12 255 -1 3;\nAction: ` — and the SO-101's pick-and-place
//! prompt, with one token per state bin.
//! The real PaliGemma tokenizer has 257k entries; a vocabulary this small keeps the embedding
//! (and the committed checkpoint) tiny.

/// Special tokens, at ids 0..4 (the padding id 0 and BOS id 2 are what openpi uses).
pub const SPECIALS: [&str; 4] = ["<pad>", "<eos>", "<bos>", "<unk>"];
/// Words and punctuation of the prompts.
pub const WORDS: [&str; 28] = [
    "-", "Task", ":", "reach", "the", "red", "blue", "green", "yellow", "target", ",", "State",
    ";", "Action", "go", "to", "move", "touch", "a", ".",
    // the SO-101's `pick up the block and place it on the goal` (appended: the reach task's
    // ids stay where its checkpoints have them)
    "pick", "up", "block", "and", "place", "it", "on", "goal",
];

/// Vocabulary size (specials, the 256 state bins "0".."255", words).
pub fn vocab_len() -> usize {
    SPECIALS.len() + 256 + WORDS.len()
}

/// The `tokenizer.json` text.
pub fn tokenizer_json() -> String {
    let mut vocab = serde_json::Map::new();
    let mut id = 0u32;
    let mut add = |t: &str| {
        vocab.insert(t.to_string(), serde_json::Value::from(id));
        id += 1;
    };
    for t in SPECIALS {
        add(t);
    }
    for b in 0..256 {
        add(&b.to_string());
    }
    for t in WORDS {
        add(t);
    }
    let added: Vec<serde_json::Value> = SPECIALS
        .iter()
        .enumerate()
        .map(|(i, t)| {
            serde_json::json!({
                "id": i, "content": t, "single_word": false, "lstrip": false,
                "rstrip": false, "normalized": false, "special": true
            })
        })
        .collect();
    let v = serde_json::json!({
        "version": "1.0",
        "truncation": null,
        "padding": null,
        "added_tokens": added,
        "normalizer": null,
        "pre_tokenizer": { "type": "Whitespace" },
        "post_processor": null,
        "decoder": null,
        "model": { "type": "WordLevel", "vocab": vocab, "unk_token": "<unk>" }
    });
    serde_json::to_string_pretty(&v).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;
    use chunkrt_policy::preprocess::PromptTokenizer;

    #[test]
    fn the_task_prompt_tokenizes_without_unknowns() {
        let dir = std::env::temp_dir().join(format!("chunkrt-vocab-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("tokenizer.json");
        std::fs::write(&path, tokenizer_json()).unwrap();
        let tok = PromptTokenizer::from_file(&path).unwrap();
        std::fs::remove_dir_all(&dir).ok();
        let (ids, mask) = tok
            .tokenize("reach the red target", Some(&[-1, 0, 128, 255]), 24)
            .unwrap();
        let n = mask.iter().filter(|m| **m).count();
        let ids = &ids[..n];
        // BOS Task : reach the red target , State : - 1 0 128 255 ; Action :
        assert_eq!(n, 18, "{ids:?}");
        assert_eq!(ids[0], 2);
        assert!(!ids.contains(&3), "unknown token in {ids:?}");
        assert!(ids.iter().all(|&i| (i as usize) < vocab_len()));
        // state bins map to their own ids
        assert!(ids.contains(&(4 + 128)) && ids.contains(&(4 + 255)) && ids.contains(&4));
        assert!(vocab_len() <= 288);
    }
}
