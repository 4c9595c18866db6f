//! Parity with the reference fixtures (copied into `tests/fixtures/`, see its README), run as
//! a library call of what `equact policy check-fixtures` runs.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests may unwrap (CONVENTIONS 6)

use std::path::{Path, PathBuf};

use policy::fixtures::{check_dir, check_file, Outcome};

fn fixture_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures")
}

/// Fixture kinds this crate implements so far, with the least number of comparisons each
/// must make; each must pass.
const IMPLEMENTED: &[(&str, usize)] = &[
    ("sh_wigner", 9),
    ("s2_grid", 9),
    ("rotation_head", 9),
    ("pool_upsample", 9),
    ("linear_norm_rbf", 11),
    ("so2_conv", 14),
    ("graph_attention", 6),
    ("transblock", 6),
    ("language_encoder", 4),
    ("query_heads", 13),
    ("whole_model_small", 36),
];

#[test]
fn every_fixture_passes() {
    let reports = check_dir(&fixture_dir()).unwrap();
    assert_eq!(reports.len(), 11, "one report per fixture file");
    for r in &reports {
        println!("{}", r.line());
        if let Some((_, min)) = IMPLEMENTED.iter().find(|(n, _)| *n == r.name) {
            assert!(r.passed(), "{}", r.line());
            match &r.outcome {
                Outcome::Checked(c) => {
                    assert!(c.len() >= *min, "{}: only {} checks", r.name, c.len())
                }
                other => panic!("{}: {other:?}", r.name),
            }
        } else {
            panic!("unexpected fixture {}", r.line());
        }
    }
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("policy-fixture-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn unreadable_or_altered_fixtures_fail_with_a_reason() {
    let d = scratch("broken");
    let src = fixture_dir();
    // A truncated tensor file.
    let bytes = std::fs::read(src.join("sh_wigner.safetensors")).unwrap();
    std::fs::write(d.join("sh_wigner.safetensors"), &bytes[..1000]).unwrap();
    std::fs::copy(src.join("sh_wigner.json"), d.join("sh_wigner.json")).unwrap();
    // A tensor file without its sidecar.
    std::fs::copy(
        src.join("pool_upsample.safetensors"),
        d.join("pool_upsample.safetensors"),
    )
    .unwrap();
    // A sidecar without its tensor file.
    std::fs::copy(src.join("s2_grid.json"), d.join("s2_grid.json")).unwrap();
    let reports = check_dir(&d).unwrap();
    assert_eq!(reports.len(), 3);
    for r in &reports {
        assert!(!r.passed());
        assert!(matches!(r.outcome, Outcome::Failed(_)), "{}", r.line());
        assert!(r.line().contains("error"), "{}", r.line());
    }
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn a_wrong_reference_value_is_caught() {
    // Flip one stored output value by 1e-3: the check must fail on exactly that key.
    let d = scratch("tampered");
    let src = fixture_dir();
    let mut tensors =
        policy::fixtures::read_safetensors(&src.join("rotation_head.safetensors")).unwrap();
    let t = tensors.get_mut("out.logits").unwrap();
    if let policy::fixtures::TensorData::F32(v) = &mut t.data {
        v[17] += 1e-3;
    }
    let mut owned: Vec<(String, Vec<usize>, safetensors::Dtype, Vec<u8>)> = Vec::new();
    for (k, t) in &tensors {
        let (dtype, bytes) = match &t.data {
            policy::fixtures::TensorData::F32(v) => (
                safetensors::Dtype::F32,
                v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            ),
            policy::fixtures::TensorData::I64(v) => (
                safetensors::Dtype::I64,
                v.iter().flat_map(|x| x.to_le_bytes()).collect(),
            ),
        };
        owned.push((k.clone(), t.shape.clone(), dtype, bytes));
    }
    let views: Vec<(String, safetensors::tensor::TensorView<'_>)> = owned
        .iter()
        .map(|(k, s, dt, b)| {
            (
                k.clone(),
                safetensors::tensor::TensorView::new(*dt, s.clone(), b).unwrap(),
            )
        })
        .collect();
    safetensors::serialize_to_file(views, None, &d.join("rotation_head.safetensors")).unwrap();
    std::fs::copy(src.join("rotation_head.json"), d.join("rotation_head.json")).unwrap();
    let r = check_file(&d.join("rotation_head.safetensors"));
    assert!(!r.passed(), "{}", r.line());
    let Outcome::Checked(cs) = &r.outcome else {
        panic!("{}", r.line())
    };
    let failing: Vec<_> = cs
        .iter()
        .filter(|c| !c.passed())
        .map(|c| c.what.as_str())
        .collect();
    assert_eq!(failing, ["out.logits"]);
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn an_empty_folder_is_an_error() {
    let d = scratch("empty");
    assert!(check_dir(&d).is_err());
    assert!(check_dir(&d.join("missing")).is_err());
    std::fs::remove_dir_all(&d).unwrap();
}

#[test]
fn an_unknown_fixture_kind_is_a_failure() {
    let d = scratch("unknown");
    let src = fixture_dir();
    std::fs::copy(
        src.join("pool_upsample.safetensors"),
        d.join("mystery.safetensors"),
    )
    .unwrap();
    std::fs::write(d.join("mystery.json"), r#"{"fixture": "mystery_block"}"#).unwrap();
    let r = check_file(&d.join("mystery.safetensors"));
    assert!(!r.passed());
    assert!(matches!(r.outcome, Outcome::Unsupported(_)), "{}", r.line());
    assert!(r.line().starts_with("FAIL") && r.line().contains("mystery_block"));
    std::fs::remove_dir_all(&d).unwrap();
}
