//! Named parameter store: loads the reference's state-dict layout from safetensors and hands
//! out tensors by name, checking presence and shape.
//!
//! Parameter names are the keys of the reference module's `state_dict()` (e.g.
//! `ga.so2_conv_1.fc_m0.weight`); a [`Scope`] prefixes them, so a layer is built from the
//! scope of its module and the same code serves a fixture (`param.` prefix), a converted
//! checkpoint (no prefix) or a sub-module of the whole model.

use std::collections::{BTreeMap, HashMap};
use std::io::Read;
use std::path::Path;

use crate::error::{PolicyError, Result};
use crate::fixtures::{parse_safetensors, StoredTensor, TensorData};

/// Metadata key of the number of cloud points a network was trained with: the weights do
/// not depend on it, but a network fed another count sees sparser or denser clouds than it
/// learned from, so the inference commands take it from the file.
pub const N_POINTS_KEY: &str = "equact.n_points";

/// Metadata key of how many of those points were sampled first near the gripper
/// (`PolicyConfig::n_near_gripper`); absent means 0, as in every file from before it.
pub const NEAR_GRIPPER_POINTS_KEY: &str = "equact.near_gripper_points";

/// Metadata key of the height (m) above the table of the focus box's floor the network
/// was trained with (`PolicyConfig::focus_above_table`); absent means 0, EquAct's box.
pub const FOCUS_ABOVE_TABLE_KEY: &str = "equact.focus_above_table_m";

/// Metadata key of how trained weights came to be: a JSON array with one object per
/// training run that led to them, oldest first, each that run's settings (its `train.json`)
/// and `steps`, the optimiser steps it had taken when the file was written. `equact train`
/// writes it (a fine-tune appends its run to its initial weights' history) and `equact
/// policy info` prints it, so a weights file says what it is without the run folder.
pub const TRAINING_KEY: &str = "equact.training";

/// All tensors of one weights file, by full key, and the file's metadata.
#[derive(Debug, Clone)]
pub struct Weights {
    source: String,
    tensors: HashMap<String, StoredTensor>,
    metadata: BTreeMap<String, String>,
}

/// The number of cloud points the weights in `path` were trained with ([`N_POINTS_KEY`]),
/// read from the safetensors header alone ([`Weights::header_only`]); `None` when the file
/// does not record it (weights from before it was, or a converted reference checkpoint).
pub fn trained_points(path: &Path) -> Result<Option<usize>> {
    Weights::header_only(path)?.trained_points()
}

/// The metadata of the safetensors header of `path`, read without the tensors (a physical
/// network's file is hundreds of megabytes).
fn read_header_metadata(path: &Path) -> Result<BTreeMap<String, String>> {
    let bad = |message: String| PolicyError::Safetensors {
        path: path.to_path_buf(),
        message,
    };
    let io = |source| PolicyError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let mut len = [0u8; 8];
    file.read_exact(&mut len).map_err(io)?;
    let len = u64::from_le_bytes(len);
    // The safetensors format's own bound on the header.
    if len > 100_000_000 {
        return Err(bad(format!(
            "the header claims {len} bytes: not a safetensors file"
        )));
    }
    let mut header = vec![0u8; len as usize];
    file.read_exact(&mut header).map_err(io)?;
    let header: serde_json::Value =
        serde_json::from_slice(&header).map_err(|e| bad(format!("header: {e}")))?;
    let Some(metadata) = header.get("__metadata__").and_then(|m| m.as_object()) else {
        return Ok(BTreeMap::new());
    };
    metadata
        .iter()
        .map(|(key, v)| match v.as_str() {
            Some(text) => Ok((key.clone(), text.to_string())),
            None => Err(bad(format!("{key} is not a string"))),
        })
        .collect()
}

/// Parses a count of points recorded under `key`.
/// A safetensors file's bytes with its header's keys in sorted order (the metadata's and
/// the tensors' entries alike), padded as the crate pads it. The `safetensors` crate writes
/// the metadata in its hash map's order, which differs from process to process, so the
/// same tensors and metadata would otherwise give different files; readers take each
/// tensor's place from its offsets, not from the order.
pub fn sorted_safetensors_header(mut bytes: Vec<u8>) -> std::result::Result<Vec<u8>, String> {
    let length: [u8; 8] = bytes
        .get(..8)
        .and_then(|b| b.try_into().ok())
        .ok_or("shorter than a safetensors header length")?;
    let n = usize::try_from(u64::from_le_bytes(length))
        .map_err(|_| "header length past this machine's address space".to_string())?;
    let header = bytes
        .get(8..8 + n)
        .ok_or_else(|| format!("header of {n} bytes past the end of {} bytes", bytes.len()))?;
    // serde_json's map (without its `preserve_order` feature) is a BTreeMap: the keys come
    // out sorted.
    let value: serde_json::Value =
        serde_json::from_slice(header).map_err(|e| format!("header: {e}"))?;
    let mut text = serde_json::to_vec(&value).map_err(|e| format!("header: {e}"))?;
    // Spaces up to a multiple of 8 bytes keep the data aligned, as the crate writes it.
    text.resize(text.len().next_multiple_of(8), b' ');
    // The new header replaces the old in place: a physical network's file is hundreds of
    // megabytes, not worth a second copy (the lengths are mostly equal: nothing moves).
    let prefix = (text.len() as u64).to_le_bytes().into_iter().chain(text);
    bytes.splice(..8 + n, prefix);
    Ok(bytes)
}

fn parse_count(key: &str, value: Option<&str>) -> std::result::Result<Option<usize>, String> {
    value
        .map(|v| {
            v.parse::<usize>()
                .map_err(|_| format!("{key} is {v:?}: expected a count of points, e.g. \"512\""))
        })
        .transpose()
}

/// A view of a [`Weights`] store under a key prefix (a module path).
#[derive(Debug, Clone)]
pub struct Scope<'a> {
    weights: &'a Weights,
    prefix: String,
}

impl Weights {
    /// Reads every tensor of a safetensors file, and its metadata.
    pub fn from_file(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|source| PolicyError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_bytes(&path.display().to_string(), &bytes)
    }

    /// Parses safetensors bytes already in memory (tensors and metadata); `source` names
    /// them in error messages.
    pub fn from_bytes(source: &str, bytes: &[u8]) -> Result<Self> {
        let tensors = parse_safetensors(bytes, Path::new(source))?;
        let (_, header) = safetensors::SafeTensors::read_metadata(bytes).map_err(|e| {
            PolicyError::Safetensors {
                path: source.into(),
                message: e.to_string(),
            }
        })?;
        Ok(Self {
            source: source.to_string(),
            tensors,
            metadata: header
                .metadata()
                .clone()
                .unwrap_or_default()
                .into_iter()
                .collect(),
        })
    }

    /// The metadata of the safetensors file `path` without its tensors: enough for the
    /// `trained_*` settings and the training history, read in one pass over the header.
    pub fn header_only(path: &Path) -> Result<Self> {
        Ok(Self {
            source: path.display().to_string(),
            tensors: HashMap::new(),
            metadata: read_header_metadata(path)?,
        })
    }

    /// Wraps tensors already in memory (no metadata); `source` names them in error messages.
    pub fn from_tensors(source: &str, tensors: HashMap<String, StoredTensor>) -> Self {
        Self {
            source: source.to_string(),
            tensors,
            metadata: BTreeMap::new(),
        }
    }

    /// A metadata value (the safetensors header's `__metadata__`).
    pub fn metadata(&self, key: &str) -> Option<&str> {
        self.metadata.get(key).map(String::as_str)
    }

    /// Sets a metadata value, written by [`Weights::save`].
    pub fn set_metadata(&mut self, key: &str, value: String) {
        self.metadata.insert(key.to_string(), value);
    }

    /// The number of cloud points these weights were trained with ([`N_POINTS_KEY`]), as
    /// [`trained_points`] reads it from a file's header; `None` when not recorded.
    pub fn trained_points(&self) -> Result<Option<usize>> {
        parse_count(N_POINTS_KEY, self.metadata(N_POINTS_KEY))
            .map_err(|message| self.bad_metadata(message))
    }

    /// How many of the trained cloud points were sampled near the gripper
    /// ([`NEAR_GRIPPER_POINTS_KEY`]); `None` when not recorded (that is 0).
    pub fn trained_near_gripper_points(&self) -> Result<Option<usize>> {
        parse_count(
            NEAR_GRIPPER_POINTS_KEY,
            self.metadata(NEAR_GRIPPER_POINTS_KEY),
        )
        .map_err(|message| self.bad_metadata(message))
    }

    /// The focus box's floor above the table these weights were trained with
    /// ([`FOCUS_ABOVE_TABLE_KEY`]); `None` when not recorded (that is 0).
    pub fn trained_focus_above_table(&self) -> Result<Option<f64>> {
        let Some(text) = self.metadata(FOCUS_ABOVE_TABLE_KEY) else {
            return Ok(None);
        };
        match text.parse::<f64>() {
            Ok(h) if h.is_finite() && h >= 0.0 => Ok(Some(h)),
            _ => Err(self.bad_metadata(format!(
                "{FOCUS_ABOVE_TABLE_KEY} is {text:?}: expected a height in metres, e.g. \"0.01\""
            ))),
        }
    }

    /// The error for a metadata value of this file that cannot be read.
    fn bad_metadata(&self, message: String) -> PolicyError {
        PolicyError::Safetensors {
            path: self.source.clone().into(),
            message,
        }
    }

    /// The training runs that led to these weights ([`TRAINING_KEY`], oldest first); empty
    /// when the file does not record them (random weights, files from before the key, a
    /// converted reference checkpoint).
    pub fn training_history(&self) -> Result<Vec<serde_json::Value>> {
        let Some(text) = self.metadata(TRAINING_KEY) else {
            return Ok(Vec::new());
        };
        let bad = |why: String| PolicyError::Safetensors {
            path: self.source.clone().into(),
            message: format!(
                "metadata {TRAINING_KEY} {why}; rewrite the file without it or with a JSON \
                 array of training runs"
            ),
        };
        match serde_json::from_str(text) {
            Ok(serde_json::Value::Array(runs)) if runs.iter().all(|r| r.is_object()) => Ok(runs),
            Ok(_) => Err(bad("is not a JSON array of objects".into())),
            Err(e) => Err(bad(format!("is not JSON ({e})"))),
        }
    }

    /// Number of tensors.
    pub fn len(&self) -> usize {
        self.tensors.len()
    }

    /// Whether the store holds no tensor.
    pub fn is_empty(&self) -> bool {
        self.tensors.is_empty()
    }

    /// Total number of scalar values (parameters) over all tensors.
    pub fn num_values(&self) -> usize {
        self.tensors
            .values()
            .map(|t| t.shape.iter().product::<usize>())
            .sum()
    }

    /// All keys, sorted.
    pub fn keys(&self) -> Vec<&str> {
        let mut k: Vec<&str> = self.tensors.keys().map(String::as_str).collect();
        k.sort_unstable();
        k
    }

    /// Writes every tensor to a safetensors file (F32 and I64, little-endian, keys sorted).
    pub fn save(&self, path: &Path) -> Result<()> {
        let bad = |message: String| PolicyError::Safetensors {
            path: path.to_path_buf(),
            message,
        };
        let bytes: Vec<(&str, &[usize], safetensors::Dtype, Vec<u8>)> = self
            .keys()
            .into_iter()
            .filter_map(|k| self.tensors.get(k).map(|t| (k, t)))
            .map(|(k, t)| {
                let (dtype, raw) = match &t.data {
                    TensorData::F32(v) => (
                        safetensors::Dtype::F32,
                        v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                    ),
                    TensorData::I64(v) => (
                        safetensors::Dtype::I64,
                        v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                    ),
                };
                (k, t.shape.as_slice(), dtype, raw)
            })
            .collect();
        let mut views = Vec::with_capacity(bytes.len());
        for (k, shape, dtype, raw) in &bytes {
            let v = safetensors::tensor::TensorView::new(*dtype, shape.to_vec(), raw)
                .map_err(|e| bad(format!("{k}: {e}")))?;
            views.push((*k, v));
        }
        let metadata = (!self.metadata.is_empty()).then(|| {
            self.metadata
                .iter()
                .map(|(k, v)| (k.clone(), v.clone()))
                .collect()
        });
        let bytes = safetensors::serialize(views, metadata).map_err(|e| bad(e.to_string()))?;
        let bytes = sorted_safetensors_header(bytes).map_err(bad)?;
        std::fs::write(path, bytes).map_err(|e| PolicyError::Io {
            path: path.to_path_buf(),
            source: e,
        })
    }

    /// Where the tensors came from (for error messages).
    pub fn source(&self) -> &str {
        &self.source
    }

    /// Whether a full key is present.
    pub fn contains(&self, key: &str) -> bool {
        self.tensors.contains_key(key)
    }

    /// The root scope, with keys under `prefix` (e.g. `"param."`, or `""`).
    pub fn scope(&self, prefix: &str) -> Scope<'_> {
        Scope {
            weights: self,
            prefix: prefix.to_string(),
        }
    }

    fn raw(&self, key: &str) -> Result<&StoredTensor> {
        self.tensors
            .get(key)
            .ok_or_else(|| PolicyError::MissingTensor {
                name: key.to_string(),
                file: self.source.clone(),
            })
    }

    /// A float32 tensor with exactly the given shape.
    pub fn f32(&self, key: &str, shape: &[usize]) -> Result<Vec<f32>> {
        let (got, v) = self.f32_any(key)?;
        if got != shape {
            return Err(PolicyError::ShapeMismatch {
                name: key.to_string(),
                expected: shape.to_vec(),
                got,
            });
        }
        Ok(v)
    }

    /// A float32 tensor of any shape, with its shape.
    pub fn f32_any(&self, key: &str) -> Result<(Vec<usize>, Vec<f32>)> {
        let t = self.raw(key)?;
        match &t.data {
            TensorData::F32(v) => Ok((t.shape.clone(), v.clone())),
            TensorData::I64(_) => Err(PolicyError::WrongDtype {
                name: key.to_string(),
                expected: "F32",
                got: "I64".into(),
            }),
        }
    }

    /// The shape of a tensor.
    pub fn shape_of(&self, key: &str) -> Result<Vec<usize>> {
        Ok(self.raw(key)?.shape.clone())
    }

    /// An int64 tensor of any shape, with its shape.
    pub fn i64_any(&self, key: &str) -> Result<(Vec<usize>, Vec<i64>)> {
        let t = self.raw(key)?;
        match &t.data {
            TensorData::I64(v) => Ok((t.shape.clone(), v.clone())),
            TensorData::F32(_) => Err(PolicyError::WrongDtype {
                name: key.to_string(),
                expected: "I64",
                got: "F32".into(),
            }),
        }
    }

    /// The values of a float32 tensor, for in-place updates (the optimiser).
    pub fn f32_mut(&mut self, key: &str) -> Result<&mut [f32]> {
        let source = self.source.clone();
        let t = self
            .tensors
            .get_mut(key)
            .ok_or_else(|| PolicyError::MissingTensor {
                name: key.to_string(),
                file: source,
            })?;
        match &mut t.data {
            TensorData::F32(v) => Ok(v),
            TensorData::I64(_) => Err(PolicyError::WrongDtype {
                name: key.to_string(),
                expected: "F32",
                got: "I64".into(),
            }),
        }
    }

    /// The shape of a tensor, checked to have `rank` axes.
    pub fn shape(&self, key: &str, rank: usize) -> Result<Vec<usize>> {
        let t = self.raw(key)?;
        if t.shape.len() != rank {
            return Err(PolicyError::ShapeMismatch {
                name: key.to_string(),
                expected: vec![0; rank],
                got: t.shape.clone(),
            });
        }
        Ok(t.shape.clone())
    }
}

impl<'a> Scope<'a> {
    /// The scope of a sub-module (`self.prefix + name + "."`).
    pub fn sub(&self, name: &str) -> Scope<'a> {
        Scope {
            weights: self.weights,
            prefix: format!("{}{}.", self.prefix, name),
        }
    }

    /// The full key of a parameter in this scope.
    pub fn key(&self, name: &str) -> String {
        format!("{}{}", self.prefix, name)
    }

    /// Whether the parameter exists in this scope.
    pub fn contains(&self, name: &str) -> bool {
        self.weights.contains(&self.key(name))
    }

    /// A float32 parameter with exactly the given shape.
    pub fn f32(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>> {
        self.weights.f32(&self.key(name), shape)
    }

    /// The shape of a parameter, checked to have `rank` axes.
    pub fn shape(&self, name: &str, rank: usize) -> Result<Vec<usize>> {
        self.weights.shape(&self.key(name), rank)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::init::random_weights;
    use crate::predict::PolicyConfig;

    #[test]
    fn metadata_round_trips_and_the_point_count_reads_from_the_header() {
        let dir = std::env::temp_dir().join(format!("equact_weights_meta_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let cfg = PolicyConfig::tiny();
        let mut w = random_weights(&cfg.model, &cfg.extra, 3);
        let file = dir.join("w.safetensors");
        // Without metadata: no count (weights from before it was recorded).
        w.save(&file).unwrap();
        assert_eq!(trained_points(&file).unwrap(), None);
        assert_eq!(
            Weights::from_file(&file).unwrap().metadata(N_POINTS_KEY),
            None
        );
        w.set_metadata(N_POINTS_KEY, "1024".into());
        w.save(&file).unwrap();
        assert_eq!(trained_points(&file).unwrap(), Some(1024));
        let back = Weights::from_file(&file).unwrap();
        assert_eq!(back.metadata(N_POINTS_KEY), Some("1024"));
        assert_eq!(back.num_values(), w.num_values());
        // A malformed count and a file that is not safetensors are named, not guessed.
        w.set_metadata(N_POINTS_KEY, "many".into());
        w.save(&file).unwrap();
        let err = trained_points(&file).unwrap_err().to_string();
        assert!(
            err.contains("\"many\"") && err.contains("w.safetensors"),
            "{err}"
        );
        let loaded = Weights::from_file(&file).unwrap().trained_points();
        assert_eq!(loaded.unwrap_err().to_string(), err);
        std::fs::write(&file, b"\xff\xff\xff\xff\xff\xff\xff\xffjunk").unwrap();
        let err = trained_points(&file).unwrap_err().to_string();
        assert!(err.contains("not a safetensors file"), "{err}");
        std::fs::write(&file, b"\x04\x00").unwrap();
        assert!(trained_points(&file).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_same_weights_and_metadata_save_to_the_same_bytes() {
        let dir = std::env::temp_dir().join(format!("equact_weights_same_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let cfg = PolicyConfig::tiny();
        let mut w = random_weights(&cfg.model, &cfg.extra, 5);
        // Six keys: the crate's hash map orders them differently from one map to the next.
        for key in ["a", "format", "n", "seed", "task", "z"] {
            w.set_metadata(key, format!("value of {key}"));
        }
        let file = dir.join("w.safetensors");
        w.save(&file).unwrap();
        let first = std::fs::read(&file).unwrap();
        for _ in 0..8 {
            w.save(&file).unwrap();
            assert!(std::fs::read(&file).unwrap() == first);
        }
        // Still a safetensors file with the same tensors and metadata, its data aligned.
        let back = Weights::from_file(&file).unwrap();
        for key in w.keys() {
            assert_eq!(
                back.f32_any(key).unwrap().1,
                w.f32_any(key).unwrap().1,
                "{key}"
            );
        }
        assert_eq!(back.metadata("task"), Some("value of task"));
        let n = u64::from_le_bytes(first[..8].try_into().unwrap()) as usize;
        assert_eq!(n % 8, 0);
        assert!(safetensors::SafeTensors::deserialize(&first).is_ok());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_header_that_is_not_safetensors_is_named() {
        assert!(sorted_safetensors_header(vec![1, 2])
            .unwrap_err()
            .contains("shorter"));
        let mut past = 100u64.to_le_bytes().to_vec();
        past.extend_from_slice(b"{}");
        assert!(sorted_safetensors_header(past)
            .unwrap_err()
            .contains("past the end"));
        let mut junk = 4u64.to_le_bytes().to_vec();
        junk.extend_from_slice(b"{{{{");
        assert!(sorted_safetensors_header(junk)
            .unwrap_err()
            .contains("header"));
    }
}
