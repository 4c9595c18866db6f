//! Named parameter store: loads the reference's state-dict layout from safetensors and hands
//! out tensors by name, checking presence and shape.
//!
//! Parameter names are the keys of the reference module's `state_dict()` (e.g.
//! `ga.so2_conv_1.fc_m0.weight`); a [`Scope`] prefixes them, so a layer is built from the
//! scope of its module and the same code serves a fixture (`param.` prefix), a converted
//! checkpoint (no prefix) or a sub-module of the whole model.

use std::collections::HashMap;
use std::path::Path;

use crate::error::{PolicyError, Result};
use crate::fixtures::{read_safetensors, StoredTensor, TensorData};

/// All tensors of one weights file, by full key.
#[derive(Debug, Clone)]
pub struct Weights {
    source: String,
    tensors: HashMap<String, StoredTensor>,
}

/// A view of a [`Weights`] store under a key prefix (a module path).
#[derive(Debug, Clone)]
pub struct Scope<'a> {
    weights: &'a Weights,
    prefix: String,
}

impl Weights {
    /// Reads every tensor of a safetensors file.
    pub fn from_file(path: &Path) -> Result<Self> {
        Ok(Self {
            source: path.display().to_string(),
            tensors: read_safetensors(path)?,
        })
    }

    /// Wraps tensors already in memory; `source` names them in error messages.
    pub fn from_tensors(source: &str, tensors: HashMap<String, StoredTensor>) -> Self {
        Self {
            source: source.to_string(),
            tensors,
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
        safetensors::serialize_to_file(views, None, path).map_err(|e| bad(e.to_string()))
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
