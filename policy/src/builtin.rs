//! The model that ships with the repository, compiled into the binary so that `equact run`
//! needs no model file: the CPU-configuration network trained on the simulated cell's expert
//! demonstrations (`weights/cpu_gated.safetensors`: [`PolicyConfig::cpu`] fed [`POINTS`]
//! cloud points, gated mode, equivariant heads; how it was trained and how well it does is
//! in the README's Training section), and the all-MiniLM-L6-v2 per-token states of the
//! simulated tasks' instructions (`weights/minilm_instructions.safetensors`, one
//! `[tokens, 384]` tensor keyed by the instruction's text), so the instructions need neither
//! the Python package of the sentence model nor its files.
//!
//! The embeddings are looked up by text, not by task name: an instruction whose wording
//! changed has no entry and is refused with the known texts listed, instead of silently
//! running on the old wording's embedding. The test suite checks every entry against the
//! MiniLM encoder (`tests/tests/minilm.rs`).

use crate::error::{PolicyError, Result};
use crate::predict::{InstructionEmbedding, Policy, PolicyConfig};
use crate::weights::Weights;

/// Where the built-in weights live in the repository (named in messages and recordings).
pub const WEIGHTS_PATH: &str = "policy/weights/cpu_gated.safetensors";

/// Where the built-in instruction embeddings live in the repository.
pub const INSTRUCTIONS_PATH: &str = "policy/weights/minilm_instructions.safetensors";

const WEIGHTS: &[u8] = include_bytes!("../weights/cpu_gated.safetensors");
const INSTRUCTIONS: &[u8] = include_bytes!("../weights/minilm_instructions.safetensors");

/// Cloud points the built-in network was trained with (twice [`PolicyConfig::cpu`]'s
/// default: its last 900 training steps were at this density; the weights file records the
/// count).
pub const POINTS: usize = 1024;

/// The network configuration the built-in weights were trained with (before it is adapted
/// to a cell's workspace).
pub fn config() -> PolicyConfig {
    PolicyConfig::cpu().with_points(POINTS)
}

/// The built-in weights as a parameter store.
pub fn weights() -> Result<Weights> {
    Weights::from_bytes(WEIGHTS_PATH, WEIGHTS)
}

/// The built-in network, with `cfg` (the built-in [`config`], adapted to the cell).
pub fn policy(cfg: PolicyConfig) -> Result<Policy> {
    Policy::from_weights(cfg, &weights()?)
}

fn instruction_store() -> Result<Weights> {
    Weights::from_bytes(INSTRUCTIONS_PATH, INSTRUCTIONS)
}

/// The instructions that have a built-in embedding, sorted.
pub fn instructions() -> Result<Vec<String>> {
    Ok(instruction_store()?
        .keys()
        .into_iter()
        .map(str::to_string)
        .collect())
}

/// The built-in MiniLM embedding of `text` (exactly as worded); an instruction without one
/// is refused with the known texts listed.
pub fn instruction(text: &str) -> Result<InstructionEmbedding> {
    let store = instruction_store()?;
    if !store.contains(text) {
        return Err(PolicyError::BadInstruction {
            what: format!(
                "no built-in embedding of `{text}` (the built-in ones: {}); embed free text \
                 with the MiniLM model (--minilm DIR) or pass an embedding file",
                store
                    .keys()
                    .iter()
                    .map(|k| format!("`{k}`"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        });
    }
    let (shape, values) = store.f32_any(text)?;
    let [tokens, dim] = shape[..] else {
        return Err(PolicyError::ShapeMismatch {
            name: format!("{text} in {INSTRUCTIONS_PATH}"),
            expected: vec![0, crate::minilm::HIDDEN],
            got: shape,
        });
    };
    InstructionEmbedding::new(values, tokens, dim)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]

    use super::*;

    #[test]
    fn the_builtin_weights_load_into_the_cpu_configuration() {
        let w = weights().unwrap();
        // Every parameter of the cpu network is present with its shape (a missing or
        // misshapen one is an error naming it), and nothing else is in the file.
        let policy = policy(config()).unwrap();
        assert_eq!(policy.config().n_points, POINTS);
        // The file says so too, as a trained model's file does for `--model`.
        assert_eq!(
            w.metadata(crate::weights::N_POINTS_KEY),
            Some(POINTS.to_string().as_str())
        );
        // And how it was trained: three runs, all with instruction pairs and sibling
        // negatives, the first from random weights, the last 900 steps at these points
        // (the README's reproduction chain).
        let runs = w.training_history().unwrap();
        let steps: Vec<_> = runs.iter().map(|r| r["steps"].as_u64()).collect();
        assert_eq!(steps, [Some(6000), Some(2400), Some(900)]);
        assert!(runs
            .iter()
            .all(|r| r["paired"] == true && r["sibling_negatives"] == true));
        let last = &runs[2];
        assert_eq!(
            (last["points"].as_u64(), last["levels"].as_u64()),
            (Some(POINTS as u64), Some(3))
        );
        let cfg = config();
        let fresh = crate::init::random_weights(&cfg.model, &cfg.extra, 0);
        assert_eq!(w.keys(), fresh.keys());
        assert_eq!(w.num_values(), fresh.num_values());
    }

    #[test]
    fn builtin_instructions_are_minilm_states_looked_up_by_text() {
        let texts = instructions().unwrap();
        assert_eq!(texts.len(), 11, "{texts:?}");
        for t in &texts {
            let e = instruction(t).unwrap();
            assert_eq!(e.dim(), crate::minilm::HIDDEN, "{t}");
            // [CLS], the words, [SEP]: at least three tokens.
            assert!(e.tokens() >= 3, "{t}: {} tokens", e.tokens());
            assert!(e.values().iter().all(|v| v.is_finite()));
        }
        let err = instruction("pick up the banana").unwrap_err().to_string();
        assert!(
            err.contains("no built-in embedding of `pick up the banana`"),
            "{err}"
        );
        assert!(err.contains("`pick up the peach`"), "{err}");
        assert!(err.contains("--minilm"), "{err}");
    }
}
