//! transformers' `CLIPTokenizer` (the slow, file-based one the official pipeline loads from the
//! weights folder's `tokenizer/`): byte-level BPE over `vocab.json` and `merges.txt`, with the
//! special tokens and `model_max_length` of `tokenizer_config.json` / `special_tokens_map.json`,
//! called as the pipeline calls it (`padding="max_length"`, `truncation=True`).
//!
//! Written here rather than taken from the `tokenizers` crate: that crate reads a `tokenizer.json`,
//! which the official folder does not have, so its CLIP pipeline would have to be assembled from the
//! same four files piece by piece (and it brings a C regex library by default); the BPE loop itself
//! is a few dozen lines.
//!
//! Special tokens: transformers registers the special tokens (start, end, unknown and pad) as added
//! tokens and splits the raw text on them before anything else, so they map straight to their ids
//! wherever they occur. With SD-2.x's pad token "!" this means an exclamation mark in a prompt
//! becomes id 0 (the pad id), not the BPE symbol "!</w>"; the port does the same.
//!
//! Text cleanup: transformers lower-cases and collapses whitespace (after `ftfy` when installed, or
//! its `BasicTokenizer` otherwise, which also NFC-normalises and strips accents). This port does the
//! lower-casing and whitespace collapse only, which gives the same ids for ASCII text (IDArb's prompts
//! are ASCII); non-ASCII letters are kept as they are.
use anyhow::{bail, Context, Result};
use regex::Regex;
use serde_json::Value;
use std::collections::HashMap;
use std::path::Path;

/// The vocabulary file of the folder.
pub const VOCAB_FILE: &str = "vocab.json";
/// The ranked merges of the folder (first line a `#version` header).
pub const MERGES_FILE: &str = "merges.txt";
pub const TOKENIZER_CONFIG_FILE: &str = "tokenizer_config.json";
pub const SPECIAL_TOKENS_MAP_FILE: &str = "special_tokens_map.json";
/// Most merges transformers reads from `merges.txt`: CLIP's 49152-entry BPE table less the 256
/// byte symbols and the 2 special tokens (`bpe_merges[1 : 49152 - 256 - 2 + 1]`).
const MAX_MERGES: usize = 49152 - 256 - 2;
/// Marks the last symbol of a word (CLIP's BPE is word-final aware).
const END_OF_WORD: &str = "</w>";
const START_OF_TEXT: &str = "<|startoftext|>";
const END_OF_TEXT: &str = "<|endoftext|>";
/// CLIP's pre-tokenisation: special tokens, English contractions, runs of letters, single digits,
/// runs of other non-space symbols (case-insensitive, as transformers compiles it).
const WORD_PATTERN: &str = r"(?i)<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+";

#[derive(Debug, Clone)]
pub struct ClipTokenizer {
    encoder: HashMap<String, u32>,
    /// Rank of each merge (lower merges first), keyed by the pair.
    bpe_ranks: HashMap<(String, String), usize>,
    /// GPT-2's reversible byte → printable character table.
    byte_encoder: [char; 256],
    pattern: Regex,
    /// The special tokens' texts and ids, longest first (the raw text is split on them).
    special: Vec<(String, u32)>,
    pub bos_token_id: u32,
    pub eos_token_id: u32,
    pub pad_token_id: u32,
    pub model_max_length: usize,
}

/// GPT-2 / CLIP `bytes_to_unicode`: printable Latin-1 bytes map to themselves, the other 68 bytes
/// to the characters from U+0100 on, in byte order.
fn bytes_to_unicode() -> [char; 256] {
    let printable = |b: u32| (0x21..=0x7e).contains(&b) || (0xa1..=0xac).contains(&b) || (0xae..=0xff).contains(&b);
    let mut table = ['\0'; 256];
    let mut next = 256u32;
    for b in 0..256u32 {
        table[b as usize] = if printable(b) {
            char::from_u32(b).expect("Latin-1 code point")
        } else {
            next += 1;
            char::from_u32(next - 1).expect("code point below U+0200")
        };
    }
    table
}

/// A special token's text in a tokenizer JSON: a string, or an `AddedToken` object's `content`.
fn token_text(v: &Value) -> Option<String> {
    v.as_str().map(str::to_string).or_else(|| v.get("content").and_then(Value::as_str).map(str::to_string))
}

fn read_json(path: &Path) -> Result<Value> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

impl ClipTokenizer {
    /// Load a diffusers `tokenizer/` folder.
    pub fn from_dir(dir: &Path) -> Result<Self> {
        let vocab_path = dir.join(VOCAB_FILE);
        let encoder: HashMap<String, u32> = serde_json::from_value(read_json(&vocab_path)?)
            .with_context(|| format!("{}: not a map from token to id", vocab_path.display()))?;
        let merges_path = dir.join(MERGES_FILE);
        let merges = std::fs::read_to_string(&merges_path).with_context(|| format!("reading {}", merges_path.display()))?;
        let mut bpe_ranks = HashMap::new();
        // transformers drops the first line (the `#version` header) and reads the rest in order
        for (n, line) in merges.trim().lines().enumerate().skip(1).take(MAX_MERGES) {
            let rank = n - 1;
            let mut parts = line.split_whitespace();
            match (parts.next(), parts.next(), parts.next()) {
                (Some(a), Some(b), None) => {
                    bpe_ranks.insert((a.to_string(), b.to_string()), rank);
                }
                _ => bail!("{} line {}: `{line}` is not a merge of two symbols", merges_path.display(), n + 1),
            }
        }

        // special tokens: the config first, the special-tokens map over it (transformers' order)
        let mut tokens: HashMap<&str, String> = HashMap::new();
        let mut max_len = None;
        for file in [TOKENIZER_CONFIG_FILE, SPECIAL_TOKENS_MAP_FILE] {
            let path = dir.join(file);
            if !path.is_file() {
                continue;
            }
            let json = read_json(&path)?;
            for key in ["bos_token", "eos_token", "pad_token", "unk_token"] {
                if let Some(t) = json.get(key).and_then(token_text) {
                    tokens.insert(key, t);
                }
            }
            if let Some(n) = json.get("model_max_length").and_then(Value::as_u64) {
                max_len = Some(n as usize);
            }
        }
        let config_path = dir.join(TOKENIZER_CONFIG_FILE);
        let model_max_length = max_len.with_context(|| format!("{}: no model_max_length (the padded prompt length)", config_path.display()))?;
        // CLIPTokenizer's defaults where the files name none
        let text_of = |key: &str, default: &str| tokens.get(key).map(String::as_str).unwrap_or(default).to_string();
        let id = |t: &str, key: &str| -> Result<u32> {
            encoder.get(t).copied().with_context(|| format!("{}: the {key} `{t}` is not in the vocabulary", vocab_path.display()))
        };
        let mut special = Vec::new();
        for (key, default) in [("bos_token", START_OF_TEXT), ("eos_token", END_OF_TEXT), ("pad_token", END_OF_TEXT), ("unk_token", END_OF_TEXT)] {
            let t = text_of(key, default);
            special.push((t.clone(), id(&t, key)?));
        }
        let [bos, eos, pad, _] = [0, 1, 2, 3].map(|k| special[k].1);
        special.sort_by_key(|(t, _)| std::cmp::Reverse(t.len()));
        special.dedup();
        Ok(Self {
            special,
            bos_token_id: bos,
            eos_token_id: eos,
            pad_token_id: pad,
            model_max_length,
            encoder,
            bpe_ranks,
            byte_encoder: bytes_to_unicode(),
            pattern: Regex::new(WORD_PATTERN).expect("constant pattern"),
        })
    }

    /// BPE symbols of one pre-token (already byte-encoded): merge the lowest-ranked adjacent pair,
    /// everywhere it occurs, until no pair has a rank.
    fn bpe(&self, token: &str) -> Vec<String> {
        let chars: Vec<char> = token.chars().collect();
        let Some((last, init)) = chars.split_last() else { return Vec::new() };
        let mut word: Vec<String> = init.iter().map(|c| c.to_string()).collect();
        word.push(format!("{last}{END_OF_WORD}"));
        while word.len() > 1 {
            let best = word
                .windows(2)
                .filter_map(|w| self.bpe_ranks.get(&(w[0].clone(), w[1].clone())).map(|&r| (r, (w[0].clone(), w[1].clone()))))
                .min_by_key(|(r, _)| *r);
            let Some((_, (a, b))) = best else { break };
            let mut merged = Vec::with_capacity(word.len());
            let mut i = 0;
            while i < word.len() {
                if i + 1 < word.len() && word[i] == a && word[i + 1] == b {
                    merged.push(format!("{a}{b}"));
                    i += 2;
                } else {
                    merged.push(word[i].clone());
                    i += 1;
                }
            }
            word = merged;
        }
        word
    }

    /// Token ids of `text` without the special tokens around it: the text split on special
    /// tokens, each piece between them cleaned and BPE-encoded.
    pub fn encode(&self, text: &str) -> Result<Vec<u32>> {
        let mut ids = Vec::new();
        let mut rest = text;
        // leftmost special token, the longest one where several start at the same place
        while let Some((at, (t, id))) = (0..rest.len()).filter(|&i| rest.is_char_boundary(i)).find_map(|i| self.special.iter().find(|(t, _)| rest[i..].starts_with(t.as_str())).map(|s| (i, s))) {
            ids.extend(self.encode_piece(&rest[..at])?);
            ids.push(*id);
            rest = &rest[at + t.len()..];
        }
        ids.extend(self.encode_piece(rest)?);
        Ok(ids)
    }

    /// Token ids of text without special tokens (`_tokenize` + ids).
    fn encode_piece(&self, text: &str) -> Result<Vec<u32>> {
        let clean = text.split_whitespace().collect::<Vec<_>>().join(" ").to_lowercase();
        let mut ids = Vec::new();
        for m in self.pattern.find_iter(&clean) {
            // the two special tokens are whole symbols (CLIPTokenizer's BPE cache holds them)
            if let Some(&id) = [START_OF_TEXT, END_OF_TEXT].contains(&m.as_str()).then(|| self.encoder.get(m.as_str())).flatten() {
                ids.push(id);
                continue;
            }
            let encoded: String = m.as_str().bytes().map(|b| self.byte_encoder[b as usize]).collect();
            for sym in self.bpe(&encoded) {
                ids.push(*self.encoder.get(&sym).with_context(|| format!("BPE symbol `{sym}` of `{text}` is not in the vocabulary"))?);
            }
        }
        Ok(ids)
    }

    /// The pipeline's call: `[bos] ids [eos]`, truncated to `model_max_length` and padded to it
    /// with the pad token.
    pub fn encode_padded(&self, text: &str) -> Result<Vec<u32>> {
        let n = self.model_max_length;
        if n < 2 {
            bail!("model_max_length {n} leaves no room for the start and end tokens");
        }
        let mut ids = vec![self.bos_token_id];
        ids.extend(self.encode(text)?.into_iter().take(n - 2));
        ids.push(self.eos_token_id);
        ids.resize(n, self.pad_token_id);
        Ok(ids)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn byte_table_is_a_bijection_onto_printable_characters() {
        let t = bytes_to_unicode();
        let mut seen: Vec<char> = t.to_vec();
        seen.sort();
        seen.dedup();
        assert_eq!(seen.len(), 256);
        assert_eq!(t[b'a' as usize], 'a');
        // the first non-printable byte (0) maps to U+0100, the space (32) to U+0120 ('Ġ')
        assert_eq!(t[0], '\u{100}');
        assert_eq!(t[b' ' as usize], '\u{120}');
        assert!(t.iter().all(|c| !c.is_whitespace() && !c.is_control()));
    }

    /// A hand-made vocabulary: the merge order decides the split, and unmerged symbols stay apart.
    #[test]
    fn merges_apply_lowest_rank_first() -> Result<()> {
        let dir = std::env::temp_dir().join(format!("clip_tok_test_{}", std::process::id()));
        std::fs::create_dir_all(&dir)?;
        let vocab: Vec<&str> = vec!["a", "b", "c", "a</w>", "b</w>", "c</w>", "ab", "bc</w>", "abc</w>", "<|startoftext|>", "<|endoftext|>", "!"];
        let map: serde_json::Map<String, Value> = vocab.iter().enumerate().map(|(i, t)| (t.to_string(), Value::from(i))).collect();
        std::fs::write(dir.join(VOCAB_FILE), serde_json::to_string(&map)?)?;
        // "b c</w>" ranks before "a b": "abc" becomes a + bc</w>, not ab + c</w>
        std::fs::write(dir.join(MERGES_FILE), "#version: 0.2\nb c</w>\na b\nab c</w>\n")?;
        std::fs::write(dir.join(TOKENIZER_CONFIG_FILE), r#"{"model_max_length": 6, "pad_token": "!"}"#)?;
        let tok = ClipTokenizer::from_dir(&dir)?;
        assert_eq!(tok.encode("ABC")?, vec![0, 7]);
        // "a b" merges only inside a word: a final "b</w>" does not pair with it
        assert_eq!(tok.encode("ab  a")?, vec![0, 4, 3]);
        assert_eq!(tok.encode_padded("c")?, vec![9, 5, 10, 11, 11, 11]);
        // truncation keeps the end token
        assert_eq!(tok.encode_padded("a b c a b")?, vec![9, 3, 4, 5, 3, 10]);
        // the pad token "!" is split off the raw text and keeps its own id, even inside a word
        assert_eq!(tok.encode("a!b")?, vec![3, 11, 4]);
        assert!(tok.encode("d").is_err());
        std::fs::remove_dir_all(&dir).ok();
        Ok(())
    }
}
