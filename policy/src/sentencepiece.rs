//! SentencePiece `.model` files, as openpi uses PaliGemma's (`paligemma_tokenizer.model`), read
//! without the C++ library: the protobuf (decoded with `prost`), sentencepiece's whitespace
//! normalisation, its BPE encoding (the highest-scoring adjacent pair whose concatenation is a
//! piece merges first, ties to the left), user-defined symbols kept whole, and byte fallback
//! (`<0xXX>` pieces for what has no piece). Checked token for token against the `sentencepiece`
//! package through openpi's own tokenizer code (`tests/tokenizer_parity.rs`).
//!
//! Supported: BPE models (PaliGemma's and Gemma's) with an empty precompiled character map
//! (normalisation rule `identity`, as PaliGemma's). A Unigram model, or one with a character map
//! (`nmt_nfkc`), is refused at load with a clear error rather than tokenized differently.

use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};
use std::path::Path;

use prost::Message;

use crate::error::PolicyError;

/// `ModelProto` of `sentencepiece_model.proto`: the fields read here.
#[derive(Clone, PartialEq, Message)]
struct ModelProto {
    #[prost(message, repeated, tag = "1")]
    pieces: Vec<PieceProto>,
    #[prost(message, optional, tag = "2")]
    trainer_spec: Option<TrainerSpec>,
    #[prost(message, optional, tag = "3")]
    normalizer_spec: Option<NormalizerSpec>,
}

#[derive(Clone, PartialEq, Message)]
struct PieceProto {
    #[prost(string, optional, tag = "1")]
    piece: Option<String>,
    #[prost(float, optional, tag = "2")]
    score: Option<f32>,
    /// NORMAL 1, UNKNOWN 2, CONTROL 3, USER_DEFINED 4, UNUSED 5, BYTE 6.
    #[prost(int32, optional, tag = "3")]
    kind: Option<i32>,
}

#[derive(Clone, PartialEq, Message)]
struct TrainerSpec {
    /// UNIGRAM 1 (the default), BPE 2, WORD 3, CHAR 4.
    #[prost(int32, optional, tag = "3")]
    model_type: Option<i32>,
    #[prost(bool, optional, tag = "24")]
    treat_whitespace_as_suffix: Option<bool>,
    #[prost(bool, optional, tag = "35")]
    byte_fallback: Option<bool>,
    #[prost(string, optional, tag = "46")]
    bos_piece: Option<String>,
    #[prost(string, optional, tag = "47")]
    eos_piece: Option<String>,
}

#[derive(Clone, PartialEq, Message)]
struct NormalizerSpec {
    #[prost(string, optional, tag = "1")]
    name: Option<String>,
    #[prost(bytes = "vec", optional, tag = "2")]
    precompiled_charsmap: Option<Vec<u8>>,
    #[prost(bool, optional, tag = "3")]
    add_dummy_prefix: Option<bool>,
    #[prost(bool, optional, tag = "4")]
    remove_extra_whitespaces: Option<bool>,
    #[prost(bool, optional, tag = "5")]
    escape_whitespaces: Option<bool>,
}

const NORMAL: i32 = 1;
const UNKNOWN: i32 = 2;
const USER_DEFINED: i32 = 4;
const UNUSED: i32 = 5;
const BPE: i32 = 2;

/// The whitespace mark sentencepiece writes for a space.
const SPACE_MARK: &str = "\u{2581}";

/// A SentencePiece BPE tokenizer.
#[derive(Debug, Clone)]
pub struct SentencePiece {
    /// Pieces that text can become (normal, user-defined, unused), by text.
    pieces: HashMap<String, u32>,
    /// Every piece's score, by id.
    scores: Vec<f32>,
    /// Every piece's kind, by id.
    kinds: Vec<i32>,
    /// Pieces that are never produced from text (control, unknown, byte), by text.
    reserved: HashMap<String, u32>,
    /// User-defined symbols, matched whole before anything merges (longest first).
    user_defined: Vec<String>,
    /// `<0xXX>` piece ids (byte fallback).
    bytes: Option<Box<[u32; 256]>>,
    unk: u32,
    bos: Option<u32>,
    eos: Option<u32>,
    add_dummy_prefix: bool,
    remove_extra_whitespaces: bool,
    escape_whitespaces: bool,
    treat_whitespace_as_suffix: bool,
}

/// A candidate merge of two adjacent symbols (ordered: higher score first, then leftmost).
#[derive(Debug)]
struct Pair {
    score: f32,
    left: usize,
    right: usize,
    len: usize,
}

impl PartialEq for Pair {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}
impl Eq for Pair {}
impl PartialOrd for Pair {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Pair {
    fn cmp(&self, other: &Self) -> Ordering {
        self.score
            .total_cmp(&other.score)
            .then_with(|| other.left.cmp(&self.left))
    }
}

/// One symbol of the text being merged: a byte range of the normalised text.
#[derive(Debug, Clone, Copy)]
struct Symbol {
    start: usize,
    end: usize,
    prev: Option<usize>,
    next: Option<usize>,
    /// A user-defined symbol: never merged.
    frozen: bool,
}

impl SentencePiece {
    /// Reads a `.model` file (regular files of at most 64 MiB; PaliGemma's is 4.2 MB).
    pub fn from_file(path: &Path) -> Result<Self, PolicyError> {
        let bytes = crate::files::read_bounded(path, crate::files::MAX_SIDE_FILE_BYTES)?;
        Self::from_bytes(&bytes)
            .map_err(|e| PolicyError::Tokenizer(format!("{}: {e}", path.display())))
    }

    /// Decodes a serialised `ModelProto`.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, String> {
        if bytes.is_empty() {
            return Err("an empty file, not a SentencePiece model".into());
        }
        let proto = ModelProto::decode(bytes)
            .map_err(|e| format!("not a SentencePiece model (protobuf: {e})"))?;
        if proto.pieces.is_empty() {
            return Err(format!(
                "not a SentencePiece model: no pieces in its {} bytes",
                bytes.len()
            ));
        }
        let trainer = proto.trainer_spec.unwrap_or_default();
        let norm = proto.normalizer_spec.unwrap_or_default();
        let model_type = trainer.model_type.unwrap_or(1);
        if model_type != BPE {
            return Err(format!(
                "a SentencePiece model of type {} ({}); only BPE models (PaliGemma's, Gemma's) \
                 are supported",
                model_type,
                match model_type {
                    1 => "unigram",
                    3 => "word",
                    4 => "char",
                    _ => "unknown",
                }
            ));
        }
        if norm
            .precompiled_charsmap
            .as_ref()
            .is_some_and(|m| !m.is_empty())
        {
            return Err(format!(
                "the model normalises text with a character map (rule '{}'); only the \
                 'identity' rule (PaliGemma's) is supported",
                norm.name.as_deref().unwrap_or("?")
            ));
        }
        if proto.pieces.is_empty() || proto.pieces.len() > u32::MAX as usize / 2 {
            return Err(format!("{} pieces", proto.pieces.len()));
        }
        let mut pieces = HashMap::with_capacity(proto.pieces.len());
        let mut reserved = HashMap::new();
        let mut scores = Vec::with_capacity(proto.pieces.len());
        let mut kinds = Vec::with_capacity(proto.pieces.len());
        let mut user_defined = Vec::new();
        let mut unk = None;
        for (id, p) in proto.pieces.iter().enumerate() {
            let id = id as u32;
            let text = p.piece.clone().unwrap_or_default();
            let kind = p.kind.unwrap_or(NORMAL);
            if text.is_empty() {
                return Err(format!("piece {id} is empty"));
            }
            scores.push(p.score.unwrap_or(0.0));
            kinds.push(kind);
            if kind == UNKNOWN && unk.is_none() {
                unk = Some(id);
            }
            if kind == USER_DEFINED {
                user_defined.push(text.clone());
            }
            let map = if matches!(kind, NORMAL | USER_DEFINED | UNUSED) {
                &mut pieces
            } else {
                &mut reserved
            };
            if map.insert(text.clone(), id).is_some() {
                return Err(format!("piece '{text}' appears twice"));
            }
        }
        let unk = unk.ok_or("the model has no unknown piece")?;
        user_defined.sort_by_key(|s| std::cmp::Reverse(s.len()));
        let lookup = |s: &str| reserved.get(s).or_else(|| pieces.get(s)).copied();
        let bytes = if trainer.byte_fallback.unwrap_or(false) {
            let mut ids = Box::new([0u32; 256]);
            for (b, slot) in ids.iter_mut().enumerate() {
                *slot = lookup(&format!("<0x{b:02X}>"))
                    .ok_or_else(|| format!("byte fallback without the piece <0x{b:02X}>"))?;
            }
            Some(ids)
        } else {
            None
        };
        let bos = lookup(trainer.bos_piece.as_deref().unwrap_or("<s>"));
        let eos = lookup(trainer.eos_piece.as_deref().unwrap_or("</s>"));
        Ok(Self {
            pieces,
            scores,
            kinds,
            reserved,
            user_defined,
            bytes,
            unk,
            bos,
            eos,
            add_dummy_prefix: norm.add_dummy_prefix.unwrap_or(true),
            remove_extra_whitespaces: norm.remove_extra_whitespaces.unwrap_or(true),
            escape_whitespaces: norm.escape_whitespaces.unwrap_or(true),
            treat_whitespace_as_suffix: trainer.treat_whitespace_as_suffix.unwrap_or(false),
        })
    }

    /// Number of pieces (ids run from 0 to this, exclusive).
    pub fn vocab_size(&self) -> usize {
        self.scores.len()
    }

    /// The beginning-of-sentence id (`trainer_spec.bos_piece`, `<s>` by default; PaliGemma's
    /// `<bos>` is 2), if the model has one.
    pub fn bos_id(&self) -> Option<u32> {
        self.bos
    }

    /// The end-of-sentence id, if the model has one.
    pub fn eos_id(&self) -> Option<u32> {
        self.eos
    }

    /// The id of a piece, if the model has it.
    pub fn piece_id(&self, piece: &str) -> Option<u32> {
        self.reserved
            .get(piece)
            .or_else(|| self.pieces.get(piece))
            .copied()
    }

    /// sentencepiece's normaliser without a character map: spaces become `▁`, with the dummy
    /// prefix and the removal of extra whitespace as the model's spec says.
    pub fn normalize(&self, text: &str) -> String {
        let ws = if self.escape_whitespaces {
            SPACE_MARK
        } else {
            " "
        };
        let mut input = text;
        if self.remove_extra_whitespaces {
            input = input.trim_start_matches(' ');
        }
        let mut out = String::with_capacity(input.len() + 4);
        if input.is_empty() {
            return out;
        }
        if !self.treat_whitespace_as_suffix && self.add_dummy_prefix {
            out.push_str(ws);
        }
        let mut prev_space = self.remove_extra_whitespaces;
        for c in input.chars() {
            if c == ' ' {
                if !prev_space {
                    out.push_str(ws);
                }
                prev_space = self.remove_extra_whitespaces;
            } else {
                out.push(c);
                prev_space = false;
            }
        }
        if self.remove_extra_whitespaces {
            while out.ends_with(ws) {
                out.truncate(out.len() - ws.len());
            }
        }
        if self.treat_whitespace_as_suffix && self.add_dummy_prefix {
            out.push_str(ws);
        }
        out
    }

    /// Encodes `text` into piece ids, without BOS or EOS (sentencepiece's `encode(text)`).
    pub fn encode(&self, text: &str) -> Vec<u32> {
        let norm = self.normalize(text);
        let mut symbols: Vec<Symbol> = Vec::with_capacity(norm.len());
        let mut pos = 0;
        while pos < norm.len() {
            let rest = &norm[pos..];
            let (len, frozen) = match self.user_defined.iter().find(|u| rest.starts_with(*u)) {
                Some(u) => (u.len(), true),
                None => (rest.chars().next().map_or(1, char::len_utf8), false),
            };
            let i = symbols.len();
            symbols.push(Symbol {
                start: pos,
                end: pos + len,
                prev: i.checked_sub(1),
                next: None,
                frozen,
            });
            if i > 0 {
                symbols[i - 1].next = Some(i);
            }
            pos += len;
        }
        let mut agenda = BinaryHeap::new();
        // merges that made an unused piece: sentencepiece splits those back at the end
        let mut unused_merges: HashMap<String, (String, String)> = HashMap::new();
        for i in 1..symbols.len() {
            agenda.extend(self.candidate(&norm, &symbols, i - 1, i, &mut unused_merges));
        }
        while let Some(top) = agenda.pop() {
            let (l, r) = (symbols[top.left], symbols[top.right]);
            // stale: one side already merged into something else
            if l.start == l.end
                || r.start == r.end
                || l.next != Some(top.right)
                || r.end - l.start != top.len
            {
                continue;
            }
            symbols[top.left].end = r.end;
            symbols[top.left].next = r.next;
            if let Some(n) = r.next {
                symbols[n].prev = Some(top.left);
            }
            symbols[top.right].start = symbols[top.right].end;
            if let Some(p) = symbols[top.left].prev {
                agenda.extend(self.candidate(&norm, &symbols, p, top.left, &mut unused_merges));
            }
            if let Some(n) = symbols[top.left].next {
                agenda.extend(self.candidate(&norm, &symbols, top.left, n, &mut unused_merges));
            }
        }
        let mut pieces = Vec::with_capacity(symbols.len());
        let mut at = if symbols.is_empty() { None } else { Some(0) };
        while let Some(i) = at {
            let s = symbols[i];
            self.resegment(&norm[s.start..s.end], &unused_merges, &mut pieces);
            at = s.next;
        }
        let mut ids = Vec::with_capacity(pieces.len());
        let mut prev_unknown = false;
        for (piece, id) in pieces {
            if id != self.unk {
                ids.push(id);
                prev_unknown = false;
                continue;
            }
            match &self.bytes {
                Some(bytes) => ids.extend(piece.bytes().map(|b| bytes[b as usize])),
                None => {
                    // consecutive unknown pieces become one unknown id
                    if !prev_unknown {
                        ids.push(self.unk);
                    }
                    prev_unknown = true;
                }
            }
        }
        ids
    }

    /// The merge of two adjacent symbols, if their concatenation is a piece.
    fn candidate(
        &self,
        norm: &str,
        symbols: &[Symbol],
        left: usize,
        right: usize,
        unused_merges: &mut HashMap<String, (String, String)>,
    ) -> Option<Pair> {
        let (l, r) = (symbols[left], symbols[right]);
        if l.frozen || r.frozen || l.start == l.end || r.start == r.end {
            return None;
        }
        let text = &norm[l.start..r.end];
        let id = *self.pieces.get(text)?;
        if self.kinds[id as usize] == UNUSED && !unused_merges.contains_key(text) {
            unused_merges.insert(
                text.to_string(),
                (
                    norm[l.start..l.end].to_string(),
                    norm[r.start..r.end].to_string(),
                ),
            );
        }
        Some(Pair {
            score: self.scores[id as usize],
            left,
            right,
            len: r.end - l.start,
        })
    }

    /// A merged piece with its id (the unknown id when it has none); an unused piece is split
    /// back into the two it was merged from, recursively.
    fn resegment<'a>(
        &self,
        piece: &'a str,
        unused_merges: &'a HashMap<String, (String, String)>,
        out: &mut Vec<(&'a str, u32)>,
    ) {
        let id = self.piece_id(piece).unwrap_or(self.unk);
        if self.kinds[id as usize] == UNUSED {
            if let Some((l, r)) = unused_merges.get(piece) {
                self.resegment(l, unused_merges, out);
                self.resegment(r, unused_merges, out);
                return;
            }
        }
        out.push((piece, id));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A hand-made model: pieces with scores, BPE, byte fallback.
    fn model(norm: NormalizerSpec, extra: &[(&str, f32, i32)]) -> SentencePiece {
        let mut pieces = vec![
            PieceProto {
                piece: Some("<pad>".into()),
                score: Some(0.0),
                kind: Some(3),
            },
            PieceProto {
                piece: Some("<eos>".into()),
                score: Some(0.0),
                kind: Some(3),
            },
            PieceProto {
                piece: Some("<bos>".into()),
                score: Some(0.0),
                kind: Some(3),
            },
            PieceProto {
                piece: Some("<unk>".into()),
                score: Some(0.0),
                kind: Some(UNKNOWN),
            },
        ];
        for b in 0..256 {
            pieces.push(PieceProto {
                piece: Some(format!("<0x{b:02X}>")),
                score: Some(0.0),
                kind: Some(6),
            });
        }
        for (p, s, k) in extra {
            pieces.push(PieceProto {
                piece: Some(p.to_string()),
                score: Some(*s),
                kind: Some(*k),
            });
        }
        let proto = ModelProto {
            pieces,
            trainer_spec: Some(TrainerSpec {
                model_type: Some(BPE),
                byte_fallback: Some(true),
                bos_piece: Some("<bos>".into()),
                eos_piece: Some("<eos>".into()),
                ..Default::default()
            }),
            normalizer_spec: Some(norm),
        };
        SentencePiece::from_bytes(&proto.encode_to_vec()).unwrap()
    }

    fn identity() -> NormalizerSpec {
        NormalizerSpec {
            name: Some("identity".into()),
            add_dummy_prefix: Some(false),
            remove_extra_whitespaces: Some(false),
            ..Default::default()
        }
    }

    #[test]
    fn merges_by_score_then_leftmost_with_byte_fallback() {
        let base = 260;
        let m = model(
            identity(),
            &[
                ("a", -1.0, NORMAL),
                ("b", -2.0, NORMAL),
                ("\u{2581}", -3.0, NORMAL),
                ("ab", -5.0, NORMAL),
                ("ba", -4.0, NORMAL),
                ("aba", -6.0, NORMAL),
                ("<x>", 0.0, USER_DEFINED),
            ],
        );
        assert_eq!(m.bos_id(), Some(2));
        assert_eq!(m.eos_id(), Some(1));
        // "aba": "ba" (-4) beats "ab" (-5), then "a"+"ba" = "aba"
        assert_eq!(m.encode("aba"), vec![base + 5]);
        // "abab": ba merges first (left 1), leaving a|ba|b; "aba" (-6) beats nothing else
        assert_eq!(m.encode("abab"), vec![base + 5, base + 1]);
        // a space is the mark; 'é' has no piece: its two UTF-8 bytes
        assert_eq!(m.encode("a é"), vec![base, base + 2, 4 + 0xC3, 4 + 0xA9]);
        // a user-defined symbol stays whole and does not merge with its neighbours
        assert_eq!(m.encode("a<x>b"), vec![base, base + 6, base + 1]);
        assert_eq!(m.encode(""), Vec::<u32>::new());
    }

    #[test]
    fn whitespace_rules_follow_the_spec() {
        let m = model(
            NormalizerSpec {
                add_dummy_prefix: Some(true),
                remove_extra_whitespaces: Some(true),
                ..Default::default()
            },
            &[],
        );
        assert_eq!(m.normalize("  a   b  "), "\u{2581}a\u{2581}b");
        let m = model(identity(), &[]);
        assert_eq!(
            m.normalize("  a   b "),
            "\u{2581}\u{2581}a\u{2581}\u{2581}\u{2581}b\u{2581}"
        );
    }

    #[test]
    fn bad_models_are_errors_not_panics() {
        assert!(SentencePiece::from_bytes(b"\xff\xff\xff").is_err());
        let e = SentencePiece::from_bytes(&[]).unwrap_err();
        assert!(e.contains("empty file") && !e.contains("unigram"), "{e}");
        let unigram = ModelProto {
            pieces: vec![PieceProto {
                piece: Some("<unk>".into()),
                score: None,
                kind: Some(UNKNOWN),
            }],
            trainer_spec: None,
            normalizer_spec: None,
        };
        let e = SentencePiece::from_bytes(&unigram.encode_to_vec()).unwrap_err();
        assert!(e.contains("unigram"), "{e}");
        let charsmap = ModelProto {
            trainer_spec: Some(TrainerSpec {
                model_type: Some(BPE),
                ..Default::default()
            }),
            normalizer_spec: Some(NormalizerSpec {
                name: Some("nmt_nfkc".into()),
                precompiled_charsmap: Some(vec![1, 2, 3]),
                ..Default::default()
            }),
            ..unigram
        };
        let e = SentencePiece::from_bytes(&charsmap.encode_to_vec()).unwrap_err();
        assert!(e.contains("nmt_nfkc"), "{e}");
    }
}
