//! The MiniLM instruction encoder (`policy::minilm`) against an independent reference: Hugging
//! Face's `tokenizers` on the model's own tokenizer.json, and a float64 numpy BERT forward
//! on the same safetensors (`tests/peers/minilm_reference.py`), for every task instruction
//! and some harder text.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic

use equact::task::TaskKind;
use policy::minilm::{MiniLm, HIDDEN};

#[test]
fn minilm_matches_the_reference_tokenizer_and_encoder() {
    let dir = tests::minilm_model_dir().unwrap();
    let model = MiniLm::load(&dir).unwrap();
    let mut sentences: Vec<String> = TaskKind::all().iter().map(|k| k.instruction()).collect();
    sentences.extend(
        [
            "Pick up the STRAWBERRY, then place it in the bowl!",
            "Café au lait; déjà-vu (naïve)…",
            "unscrewthepipeplease  x2\tnow",
        ]
        .map(String::from),
    );
    let mut args = vec!["--model-dir", dir.to_str().unwrap()];
    args.extend(sentences.iter().map(String::as_str));
    let out = tests::run_peer("minilm_reference.py", &args).unwrap();
    let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    let refs = v["sentences"].as_array().unwrap();
    assert_eq!(refs.len(), sentences.len());
    for (text, r) in sentences.iter().zip(refs) {
        let ids: Vec<u32> = r["ids"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap() as u32)
            .collect();
        assert_eq!(model.tokenizer().encode(text), ids, "tokens of {text:?}");
        let want: Vec<f64> = r["embedding"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let got = model.embed(text).unwrap();
        assert_eq!(got.len(), HIDDEN);
        let err = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (f64::from(*a) - b).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-5, "{text:?}: embedding differs by {err}");
        let (n, states) = model.token_states(text).unwrap();
        assert_eq!(n, ids.len());
        let first: Vec<f64> = r["first_state"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let err = states[..HIDDEN]
            .iter()
            .zip(&first)
            .map(|(a, b)| (f64::from(*a) - b).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-4, "{text:?}: [CLS] state differs by {err}");
    }
    // Different instructions are told apart; the same one twice is the same embedding.
    let a = model.embed("pick the strawberry").unwrap();
    let b = model.embed("pick the plum").unwrap();
    let cos: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
    assert!(cos < 0.99, "cos {cos}");
    assert_eq!(a, model.embed("pick the strawberry").unwrap());
    assert!(model.embed("   ").is_err());
}

/// The per-token states of every task instruction, as `policy::builtin` ships them.
fn builtin_store(model: &MiniLm) -> policy::weights::Weights {
    let mut tensors = std::collections::HashMap::new();
    for kind in TaskKind::all() {
        let text = kind.instruction();
        let (tokens, states) = model.token_states(&text).unwrap();
        tensors.insert(
            text,
            policy::fixtures::StoredTensor {
                shape: vec![tokens, HIDDEN],
                data: policy::fixtures::TensorData::F32(states),
            },
        );
    }
    policy::weights::Weights::from_tensors("minilm instructions", tensors)
}

#[test]
fn builtin_instruction_embeddings_are_the_encoders_states_of_every_task_instruction() {
    let model = MiniLm::load(&tests::minilm_model_dir().unwrap()).unwrap();
    let want = builtin_store(&model);
    let shipped = policy::builtin::instructions().unwrap();
    assert_eq!(
        shipped,
        want.keys(),
        "the built-in instructions differ from the tasks' (a wording changed?): run \
         `cargo test -p tests --test minilm -- --ignored regenerate_builtin_instructions`"
    );
    for text in &shipped {
        let got = policy::builtin::instruction(text).unwrap();
        let (shape, values) = want.f32_any(text).unwrap();
        assert_eq!(vec![got.tokens(), got.dim()], shape, "{text}");
        let err = got
            .values()
            .iter()
            .zip(&values)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(
            err <= 1e-6,
            "{text}: the built-in embedding differs by {err}"
        );
    }
}

/// Writes `policy/weights/minilm_instructions.safetensors` from the task instructions (run by
/// hand after changing an instruction's wording; the test above guards the committed file).
#[test]
#[ignore = "generator: writes policy/weights/minilm_instructions.safetensors"]
fn regenerate_builtin_instructions() {
    let model = MiniLm::load(&tests::minilm_model_dir().unwrap()).unwrap();
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(policy::builtin::INSTRUCTIONS_PATH);
    builtin_store(&model).save(&path).unwrap();
}
