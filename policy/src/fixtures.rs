//! Parity checks against the reference's numerical fixtures (`equact_fixtures` format).
//!
//! Spec: the fixtures README ("Loading", "Key prefixes", "Parity tolerances"). A fixture is a
//! `NAME.safetensors` tensor file plus a `NAME.json` sidecar whose `fixture` field names the
//! building block. [`check_dir`] checks every pair in a folder and returns one report per
//! fixture; a fixture this crate cannot check yet, or a file that cannot be read, is a
//! failure, never silently skipped.
//!
//! Tolerance: an element passes when |ours - ref| <= tol · (1 + |ref|), with tol = 1e-5 for
//! plain values and 5e-5 wherever Wigner matrices enter (ours are exact, the reference's come
//! from J tables accurate to about 6e-6). Index records (FPS, kNN picks) must match exactly.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use nalgebra::Matrix3;

use crate::error::{PolicyError, Result};
use crate::grids::{reduced_coefficients, s2_healpix_grid, so3_healpix_grid, S2Grid};
use crate::points::{
    coefficient_max_pool, farthest_point_sampling, knn, upsample, upsample_weights,
    UpsampleDistance,
};
use crate::rotation_head::{flat_wigner, RotationHead, SO3_COEFFS};
use crate::so3::{
    angles_to_xyz, edge_rot_mat, matrix_to_angles, num_coefficients, spherical_harmonics,
    xyz_to_angles, WignerCalculator,
};
use crate::weights::Weights;

/// Tolerance for values that do not involve Wigner matrices.
pub const TOL: f64 = 1e-5;
/// Tolerance where the reference's tabulated Wigner matrices enter.
pub const TOL_WIGNER: f64 = 5e-5;

/// The data of one stored tensor.
#[derive(Debug, Clone)]
pub enum TensorData {
    /// float32 values.
    F32(Vec<f32>),
    /// int64 values (indices).
    I64(Vec<i64>),
}

/// One stored tensor: shape and row-major data.
#[derive(Debug, Clone)]
pub struct StoredTensor {
    /// Shape.
    pub shape: Vec<usize>,
    /// Values.
    pub data: TensorData,
}

/// A loaded safetensors file with its JSON sidecar.
#[derive(Debug, Clone)]
pub struct FixtureFile {
    /// The tensor file.
    pub path: PathBuf,
    /// All tensors by key.
    pub tensors: HashMap<String, StoredTensor>,
    /// The parsed sidecar.
    pub sidecar: serde_json::Value,
}

/// Reads every tensor of a safetensors file (F32 and I64 only).
pub fn read_safetensors(path: &Path) -> Result<HashMap<String, StoredTensor>> {
    let bytes = std::fs::read(path).map_err(|source| PolicyError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse_safetensors(&bytes, path)
}

/// Parses every tensor of safetensors bytes (F32 and I64 only); `source` names them in
/// errors (a file, or the model compiled into the binary).
pub fn parse_safetensors(bytes: &[u8], source: &Path) -> Result<HashMap<String, StoredTensor>> {
    let st =
        safetensors::SafeTensors::deserialize(bytes).map_err(|e| PolicyError::Safetensors {
            path: source.to_path_buf(),
            message: e.to_string(),
        })?;
    let mut out = HashMap::new();
    for (name, view) in st.tensors() {
        let raw = view.data();
        let data = match view.dtype() {
            safetensors::Dtype::F32 => TensorData::F32(
                raw.chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect(),
            ),
            safetensors::Dtype::I64 => TensorData::I64(
                raw.chunks_exact(8)
                    .map(|b| i64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
                    .collect(),
            ),
            other => {
                return Err(PolicyError::WrongDtype {
                    name,
                    expected: "F32 or I64",
                    got: format!("{other:?}"),
                })
            }
        };
        out.insert(
            name,
            StoredTensor {
                shape: view.shape().to_vec(),
                data,
            },
        );
    }
    Ok(out)
}

impl FixtureFile {
    /// Loads `NAME.safetensors` and its sidecar `NAME.json`.
    pub fn load(path: &Path) -> Result<Self> {
        let tensors = read_safetensors(path)?;
        let json_path = path.with_extension("json");
        let text = std::fs::read_to_string(&json_path).map_err(|source| PolicyError::Io {
            path: json_path.clone(),
            source,
        })?;
        let sidecar = serde_json::from_str(&text).map_err(|e| PolicyError::Sidecar {
            path: json_path,
            message: e.to_string(),
        })?;
        Ok(Self {
            path: path.to_path_buf(),
            tensors,
            sidecar,
        })
    }

    /// The building block this fixture exercises (sidecar `fixture`, else the file stem).
    pub fn kind(&self) -> String {
        self.sidecar
            .get("fixture")
            .and_then(|v| v.as_str())
            .map(str::to_string)
            .unwrap_or_else(|| {
                self.path
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default()
            })
    }

    fn get(&self, key: &str) -> Result<&StoredTensor> {
        self.tensors
            .get(key)
            .ok_or_else(|| PolicyError::MissingTensor {
                name: key.to_string(),
                file: self.path.display().to_string(),
            })
    }

    /// A float32 tensor, checked against an expected shape (`None` entries match anything).
    pub fn f32(&self, key: &str, shape: &[Option<usize>]) -> Result<(&[usize], &[f32])> {
        let t = self.get(key)?;
        check_shape(key, &t.shape, shape)?;
        match &t.data {
            TensorData::F32(v) => Ok((&t.shape, v)),
            TensorData::I64(_) => Err(PolicyError::WrongDtype {
                name: key.to_string(),
                expected: "F32",
                got: "I64".into(),
            }),
        }
    }

    /// A float32 tensor of any shape.
    pub fn f32_any(&self, key: &str) -> Result<(&[usize], &[f32])> {
        let t = self.get(key)?;
        match &t.data {
            TensorData::F32(v) => Ok((&t.shape, v)),
            TensorData::I64(_) => Err(PolicyError::WrongDtype {
                name: key.to_string(),
                expected: "F32",
                got: "I64".into(),
            }),
        }
    }

    /// The fixture's tensors as a parameter store (keys unchanged, e.g. `param.x.weight`).
    pub fn weights(&self) -> Weights {
        Weights::from_tensors(&self.path.display().to_string(), self.tensors.clone())
    }

    /// An int64 tensor, checked against an expected shape.
    pub fn i64(&self, key: &str, shape: &[Option<usize>]) -> Result<(&[usize], &[i64])> {
        let t = self.get(key)?;
        check_shape(key, &t.shape, shape)?;
        match &t.data {
            TensorData::I64(v) => Ok((&t.shape, v)),
            TensorData::F32(_) => Err(PolicyError::WrongDtype {
                name: key.to_string(),
                expected: "I64",
                got: "F32".into(),
            }),
        }
    }
}

fn check_shape(key: &str, got: &[usize], expected: &[Option<usize>]) -> Result<()> {
    let ok = got.len() == expected.len()
        && got
            .iter()
            .zip(expected)
            .all(|(g, e)| e.is_none_or(|e| e == *g));
    if !ok {
        return Err(PolicyError::ShapeMismatch {
            name: key.to_string(),
            expected: expected.iter().map(|e| e.unwrap_or(0)).collect(),
            got: got.to_vec(),
        });
    }
    Ok(())
}

/// The result of comparing one output with its reference.
#[derive(Debug, Clone)]
pub struct Comparison {
    /// What was compared (usually the reference key).
    pub what: String,
    /// max |ours - ref| (for index records: the number of mismatches).
    pub max_abs: f64,
    /// max_abs / max |ref|.
    pub rel: f64,
    /// max |ours - ref| / (1 + |ref|), the quantity held to the tolerance.
    pub scaled: f64,
    /// The tolerance on `scaled`.
    pub tolerance: f64,
}

impl Comparison {
    /// Whether the comparison is within tolerance (NaN fails).
    pub fn passed(&self) -> bool {
        self.scaled <= self.tolerance
    }
}

/// Compares values; a length mismatch is an infinite error.
pub fn compare(what: &str, ours: &[f64], reference: &[f32], tolerance: f64) -> Comparison {
    if ours.len() != reference.len() {
        return Comparison {
            what: format!(
                "{what} (length {} vs reference {})",
                ours.len(),
                reference.len()
            ),
            max_abs: f64::INFINITY,
            rel: f64::INFINITY,
            scaled: f64::INFINITY,
            tolerance,
        };
    }
    let mut max_abs = 0.0f64;
    let mut max_ref = 0.0f64;
    let mut scaled = 0.0f64;
    for (a, b) in ours.iter().zip(reference) {
        let b = f64::from(*b);
        let d = (a - b).abs();
        // NaN must fail: f64::max ignores NaN, so map it to infinity.
        let d = if d.is_nan() { f64::INFINITY } else { d };
        max_abs = max_abs.max(d);
        max_ref = max_ref.max(b.abs());
        scaled = scaled.max(d / (1.0 + b.abs()));
    }
    Comparison {
        what: what.to_string(),
        max_abs,
        rel: if max_ref > 0.0 {
            max_abs / max_ref
        } else {
            max_abs
        },
        scaled,
        tolerance,
    }
}

fn compare_f32(what: &str, ours: &[f32], reference: &[f32], tolerance: f64) -> Comparison {
    let o: Vec<f64> = ours.iter().map(|v| f64::from(*v)).collect();
    compare(what, &o, reference, tolerance)
}

/// Compares index records exactly: `max_abs` counts mismatches.
pub fn compare_indices(what: &str, ours: &[usize], reference: &[i64]) -> Comparison {
    let mismatches = if ours.len() != reference.len() {
        f64::INFINITY
    } else {
        ours.iter()
            .zip(reference)
            .filter(|(a, b)| **a as i64 != **b)
            .count() as f64
    };
    Comparison {
        what: what.to_string(),
        max_abs: mismatches,
        rel: mismatches,
        scaled: mismatches,
        tolerance: 0.0,
    }
}

/// What checking one fixture gave.
#[derive(Debug)]
#[non_exhaustive]
pub enum Outcome {
    /// Checked: every comparison made.
    Checked(Vec<Comparison>),
    /// This crate cannot check that kind of fixture yet (a failure).
    Unsupported(String),
    /// The fixture could not be read or did not have the expected layout (a failure).
    Failed(PolicyError),
}

/// The report of one fixture file.
#[derive(Debug)]
pub struct FixtureReport {
    /// The fixture's name (file stem).
    pub name: String,
    /// What happened.
    pub outcome: Outcome,
}

impl FixtureReport {
    /// Whether the fixture was checked and every comparison passed.
    pub fn passed(&self) -> bool {
        match &self.outcome {
            Outcome::Checked(c) => !c.is_empty() && c.iter().all(Comparison::passed),
            _ => false,
        }
    }

    /// The comparison with the largest tolerance ratio, if any.
    pub fn worst(&self) -> Option<&Comparison> {
        match &self.outcome {
            Outcome::Checked(c) => c.iter().max_by(|a, b| ratio(a).total_cmp(&ratio(b))),
            _ => None,
        }
    }

    /// One summary line: status, name, max abs and relative error, worst comparison.
    pub fn line(&self) -> String {
        let status = if self.passed() { "PASS" } else { "FAIL" };
        match &self.outcome {
            Outcome::Checked(c) => {
                let max_abs = c.iter().map(|x| x.max_abs).fold(0.0, f64::max);
                let rel = c.iter().map(|x| x.rel).fold(0.0, f64::max);
                let worst = self
                    .worst()
                    .map(|w| {
                        format!(
                            "worst {} (scaled {:.2e} / tol {:.0e})",
                            w.what, w.scaled, w.tolerance
                        )
                    })
                    .unwrap_or_default();
                format!(
                    "{status} {:<20} checks {:>3}  max_abs {:.3e}  rel {:.3e}  {worst}",
                    self.name,
                    c.len(),
                    max_abs,
                    rel
                )
            }
            Outcome::Unsupported(kind) => format!(
                "{status} {:<20} unsupported fixture kind '{kind}' (not implemented yet)",
                self.name
            ),
            Outcome::Failed(e) => format!("{status} {:<20} error: {e}", self.name),
        }
    }
}

fn ratio(c: &Comparison) -> f64 {
    if c.tolerance > 0.0 {
        c.scaled / c.tolerance
    } else if c.scaled > 0.0 {
        f64::INFINITY
    } else {
        0.0
    }
}

/// Checks every `*.safetensors` (+ `.json` sidecar) fixture in `dir`, sorted by name.
///
/// Errors only when the folder itself cannot be listed or holds no fixture; per-file problems
/// are failing reports.
pub fn check_dir(dir: &Path) -> Result<Vec<FixtureReport>> {
    let entries = std::fs::read_dir(dir).map_err(|source| PolicyError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut tensor_files = Vec::new();
    let mut sidecars = Vec::new();
    for e in entries {
        let p = e
            .map_err(|source| PolicyError::Io {
                path: dir.to_path_buf(),
                source,
            })?
            .path();
        match p.extension().and_then(|x| x.to_str()) {
            Some("safetensors") => tensor_files.push(p),
            Some("json") => sidecars.push(p),
            _ => {}
        }
    }
    tensor_files.sort();
    sidecars.sort();
    let mut reports: Vec<FixtureReport> = tensor_files.iter().map(|p| check_file(p)).collect();
    // A sidecar without its tensor file is a broken fixture too.
    for s in sidecars {
        if !s.with_extension("safetensors").exists() {
            let name = s
                .file_stem()
                .map(|x| x.to_string_lossy().into_owned())
                .unwrap_or_default();
            let source = std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "sidecar without its .safetensors file",
            );
            reports.push(FixtureReport {
                name,
                outcome: Outcome::Failed(PolicyError::Io {
                    path: s.with_extension("safetensors"),
                    source,
                }),
            });
        }
    }
    if reports.is_empty() {
        return Err(PolicyError::Io {
            path: dir.to_path_buf(),
            source: std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "no *.safetensors fixtures in this folder",
            ),
        });
    }
    Ok(reports)
}

/// Checks one fixture file.
pub fn check_file(path: &Path) -> FixtureReport {
    let name = path
        .file_stem()
        .map(|x| x.to_string_lossy().into_owned())
        .unwrap_or_default();
    let fx = match FixtureFile::load(path) {
        Ok(f) => f,
        Err(e) => {
            return FixtureReport {
                name,
                outcome: Outcome::Failed(e),
            }
        }
    };
    let kind = fx.kind();
    let result = match kind.as_str() {
        "sh_wigner" => check_sh_wigner(&fx),
        "s2_grid" => check_s2_grid(&fx),
        "rotation_head" => check_rotation_head(&fx),
        "pool_upsample" => check_pool_upsample(&fx),
        "linear_norm_rbf" => check_linear_norm_rbf(&fx),
        "so2_conv" => check_so2_conv(&fx),
        "graph_attention" => check_graph_attention(&fx),
        "transblock" => check_transblock(&fx),
        "language_encoder" => check_language_encoder(&fx),
        "query_heads" => check_query_heads(&fx),
        "whole_model_small" => check_whole_model(&fx),
        _ => {
            return FixtureReport {
                name,
                outcome: Outcome::Unsupported(kind),
            }
        }
    };
    FixtureReport {
        name,
        outcome: match result {
            Ok(c) => Outcome::Checked(c),
            Err(e) => Outcome::Failed(e),
        },
    }
}

fn mat3(v: &[f32]) -> Matrix3<f64> {
    Matrix3::from_row_slice(&v.iter().map(|x| f64::from(*x)).collect::<Vec<_>>())
}

fn vec3s(v: &[f32]) -> Vec<[f64; 3]> {
    v.chunks_exact(3)
        .map(|c| [f64::from(c[0]), f64::from(c[1]), f64::from(c[2])])
        .collect()
}

fn vec3s_f32(v: &[f32]) -> Vec<[f32; 3]> {
    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

fn flatten_dm(m: &nalgebra::DMatrix<f64>) -> Vec<f64> {
    // Row-major, like the stored tensors.
    let mut out = Vec::with_capacity(m.len());
    for r in 0..m.nrows() {
        for c in 0..m.ncols() {
            out.push(m[(r, c)]);
        }
    }
    out
}

fn sh_rows(lmax: usize, vs: &[[f64; 3]]) -> Result<Vec<f64>> {
    let mut out = Vec::with_capacity(vs.len() * num_coefficients(lmax));
    for v in vs {
        out.extend(spherical_harmonics(lmax, *v)?);
    }
    Ok(out)
}

fn check_sh_wigner(fx: &FixtureFile) -> Result<Vec<Comparison>> {
    let mut out = Vec::new();
    let calc = WignerCalculator::new(4)?;
    let (_, uv) = fx.f32("in.unit_vectors", &[None, Some(3)])?;
    let vs = vec3s(uv);
    let (_, sh) = fx.f32("out.sh", &[Some(vs.len()), Some(25)])?;
    out.push(compare("out.sh", &sh_rows(4, &vs)?, sh, TOL));
    let mut al = Vec::new();
    let mut be = Vec::new();
    for v in &vs {
        let (a, b) = xyz_to_angles(*v)?;
        al.push(a);
        be.push(b);
    }
    out.push(compare(
        "out.vec_alpha",
        &al,
        fx.f32("out.vec_alpha", &[Some(vs.len())])?.1,
        TOL,
    ));
    out.push(compare(
        "out.vec_beta",
        &be,
        fx.f32("out.vec_beta", &[Some(vs.len())])?.1,
        TOL,
    ));

    let (shape, rm) = fx.f32("in.rot_mats", &[None, Some(3), Some(3)])?;
    let nrot = shape[0];
    let (_, wref) = fx.f32("out.wigner", &[Some(nrot), Some(25), Some(25)])?;
    let mut w = Vec::new();
    let mut angles = [Vec::new(), Vec::new(), Vec::new()];
    for r in rm.chunks_exact(9) {
        let m = mat3(r);
        w.extend(flatten_dm(&calc.wigner(4, &m)?));
        let (a, b, g) = matrix_to_angles(&m)?;
        angles[0].push(a);
        angles[1].push(b);
        angles[2].push(g);
    }
    out.push(compare("out.wigner", &w, wref, TOL_WIGNER));
    for (k, key) in ["out.rot_alpha", "out.rot_beta", "out.rot_gamma"]
        .iter()
        .enumerate()
    {
        out.push(compare(key, &angles[k], fx.f32(key, &[Some(nrot)])?.1, TOL));
    }

    let (eshape, ev) = fx.f32("in.edge_vec", &[None, Some(3)])?;
    let ne = eshape[0];
    let mut erm = Vec::new();
    let mut w3 = Vec::new();
    let mut w4 = Vec::new();
    let mut w3inv = Vec::new();
    for e in vec3s(ev) {
        let m = edge_rot_mat(e)?;
        erm.extend(m.transpose().iter().copied());
        w3.extend(flatten_dm(&calc.wigner(3, &m)?));
        w3inv.extend(flatten_dm(&calc.wigner(3, &m)?.transpose()));
        w4.extend(flatten_dm(&calc.wigner(4, &m)?));
    }
    out.push(compare(
        "out.edge_rot_mat",
        &erm,
        fx.f32("out.edge_rot_mat", &[Some(ne), Some(3), Some(3)])?.1,
        TOL,
    ));
    out.push(compare(
        "out.edge_wigner_l3",
        &w3,
        fx.f32("out.edge_wigner_l3", &[Some(ne), Some(16), Some(16)])?
            .1,
        TOL_WIGNER,
    ));
    out.push(compare(
        "out.edge_wigner_inv_l3",
        &w3inv,
        fx.f32("out.edge_wigner_inv_l3", &[Some(ne), Some(16), Some(16)])?
            .1,
        TOL_WIGNER,
    ));
    out.push(compare(
        "out.edge_wigner_l4",
        &w4,
        fx.f32("out.edge_wigner_l4", &[Some(ne), Some(25), Some(25)])?
            .1,
        TOL_WIGNER,
    ));

    // The moved run: parity on the moved input, and D(R) itself.
    let r = mat3(fx.f32("rot.R", &[Some(3), Some(3)])?.1);
    out.push(compare(
        "rot.buf.D_R",
        &flatten_dm(&calc.wigner(4, &r)?),
        fx.f32("rot.buf.D_R", &[Some(25), Some(25)])?.1,
        TOL_WIGNER,
    ));
    let rvs = vec3s(fx.f32("rot.in.unit_vectors", &[Some(vs.len()), Some(3)])?.1);
    out.push(compare(
        "rot.out.sh",
        &sh_rows(4, &rvs)?,
        fx.f32("rot.out.sh", &[Some(vs.len()), Some(25)])?.1,
        TOL,
    ));
    let rev = vec3s(fx.f32("rot.in.edge_vec", &[Some(ne), Some(3)])?.1);
    let mut rerm = Vec::new();
    for e in rev {
        rerm.extend(edge_rot_mat(e)?.transpose().iter().copied());
    }
    out.push(compare(
        "rot.out.edge_rot_mat",
        &rerm,
        fx.f32("rot.out.edge_rot_mat", &[Some(ne), Some(3), Some(3)])?
            .1,
        TOL,
    ));
    Ok(out)
}

fn check_s2_grid(fx: &FixtureFile) -> Result<Vec<Comparison>> {
    let mut out = Vec::new();
    let grids = fx
        .sidecar
        .get("grids")
        .and_then(|g| g.as_object())
        .ok_or_else(|| PolicyError::Sidecar {
            path: fx.path.with_extension("json"),
            message: "missing object 'grids'".into(),
        })?;
    for (gname, g) in grids {
        let field = |k: &str| {
            g.get(k)
                .and_then(|v| v.as_u64())
                .map(|v| v as usize)
                .ok_or_else(|| PolicyError::Sidecar {
                    path: fx.path.with_extension("json"),
                    message: format!("grids.{gname}.{k} missing or not an integer"),
                })
        };
        let (lmax, mmax) = (field("lmax")?, field("mmax")?);
        let grid = S2Grid::reference(lmax, mmax)?;
        let (lat, long, nr) = (grid.lat, grid.long, grid.reduced.len());
        let shape = [Some(lat), Some(long), Some(nr)];
        out.push(compare(
            &format!("buf.to_grid_mat.{gname}"),
            &grid.to_grid,
            fx.f32(&format!("buf.to_grid_mat.{gname}"), &shape)?.1,
            TOL,
        ));
        out.push(compare(
            &format!("buf.from_grid_mat.{gname}"),
            &grid.from_grid,
            fx.f32(&format!("buf.from_grid_mat.{gname}"), &shape)?.1,
            TOL,
        ));
        out.push(compare_indices(
            &format!("buf.reduced_coef_idx.{gname}"),
            &reduced_coefficients(lmax, mmax),
            fx.i64(&format!("buf.reduced_coef_idx.{gname}"), &[Some(nr)])?
                .1,
        ));
        let betas: Vec<f64> = (0..lat)
            .map(|b| (b as f64 + 0.5) * std::f64::consts::PI / lat as f64)
            .collect();
        let alphas: Vec<f64> = (0..long)
            .map(|a| 2.0 * std::f64::consts::PI * a as f64 / long as f64)
            .collect();
        out.push(compare(
            &format!("buf.betas.{gname}"),
            &betas,
            fx.f32(&format!("buf.betas.{gname}"), &[Some(lat)])?.1,
            TOL,
        ));
        out.push(compare(
            &format!("buf.alphas.{gname}"),
            &alphas,
            fx.f32(&format!("buf.alphas.{gname}"), &[Some(long)])?.1,
            TOL,
        ));
        out.push(compare(
            &format!("buf.quadrature_weights.{gname}"),
            &crate::grids::quadrature_weights(lat, long),
            fx.f32(&format!("buf.quadrature_weights.{gname}"), &[Some(lat)])?
                .1,
            TOL,
        ));
        let (xs, x) = fx.f32(&format!("in.x.{gname}"), &[None, Some(nr), None])?;
        let (n, c) = (xs[0], xs[2]);
        out.push(compare_f32(
            &format!("out.grid.{gname}"),
            &grid.to_grid_values(x, n, c)?,
            fx.f32(
                &format!("out.grid.{gname}"),
                &[Some(n), Some(lat), Some(long), Some(c)],
            )?
            .1,
            TOL,
        ));
        out.push(compare_f32(
            &format!("out.s2act.{gname}"),
            &grid.activate(x, n, c)?,
            fx.f32(&format!("out.s2act.{gname}"), &[Some(n), Some(nr), Some(c)])?
                .1,
            TOL,
        ));
        let rkey = format!("rot.in.x.{gname}");
        if fx.tensors.contains_key(&rkey) {
            let (rs, rx) = fx.f32(&rkey, &[None, Some(nr), None])?;
            out.push(compare_f32(
                &format!("rot.out.s2act.{gname}"),
                &grid.activate(rx, rs[0], rs[2])?,
                fx.f32(
                    &format!("rot.out.s2act.{gname}"),
                    &[Some(rs[0]), Some(nr), Some(rs[2])],
                )?
                .1,
                TOL,
            ));
        }
    }
    Ok(out)
}

fn check_rotation_head(fx: &FixtureFile) -> Result<Vec<Comparison>> {
    let mut out = Vec::new();
    let calc = WignerCalculator::new(4)?;
    let kernel = s2_healpix_grid(1);
    let kg: Vec<f64> = kernel
        .iter()
        .map(|k| k.0)
        .chain(kernel.iter().map(|k| k.1))
        .collect();
    out.push(compare(
        "buf.s2_kernel_grid",
        &kg,
        fx.f32("buf.s2_kernel_grid", &[Some(2), Some(48)])?.1,
        TOL,
    ));
    let mut y = Vec::new();
    for &(a, b) in &kernel {
        y.extend(spherical_harmonics(4, angles_to_xyz(a, b))?);
    }
    out.push(compare(
        "buf.s2_conv.Y",
        &y,
        fx.f32("buf.s2_conv.Y", &[Some(48), Some(25)])?.1,
        TOL,
    ));
    for (level, n) in [(1u32, 576usize), (2, 4608)] {
        let grid = so3_healpix_grid(level);
        let angles: Vec<f64> = (0..3)
            .flat_map(|k| grid.iter().map(move |g| g.angles[k]))
            .collect();
        out.push(compare(
            &format!("buf.healpix_l{level}_angles"),
            &angles,
            fx.f32(&format!("buf.healpix_l{level}_angles"), &[Some(3), Some(n)])?
                .1,
            TOL,
        ));
        let mats: Vec<f64> = grid
            .iter()
            .flat_map(|g| g.matrix.transpose().iter().copied().collect::<Vec<_>>())
            .collect();
        out.push(compare(
            &format!("buf.healpix_l{level}_mats"),
            &mats,
            fx.f32(
                &format!("buf.healpix_l{level}_mats"),
                &[Some(n), Some(3), Some(3)],
            )?
            .1,
            TOL,
        ));
    }
    let grid = so3_healpix_grid(1);
    let fw = RotationHead::grid_wigners(&calc, &grid)?;
    let mut ow = vec![0.0; SO3_COEFFS * grid.len()];
    for (j, w) in fw.iter().enumerate() {
        for (i, v) in w.iter().enumerate() {
            ow[i * grid.len() + j] = *v;
        }
    }
    out.push(compare(
        "buf.output_wigners",
        &ow,
        fx.f32("buf.output_wigners", &[Some(SO3_COEFFS), Some(grid.len())])?
            .1,
        TOL_WIGNER,
    ));

    let (ws, w) = fx.f32("param.s2_conv.w", &[None, Some(1), Some(48)])?;
    let f_in = ws[0];
    let head = RotationHead::new(w, f_in)?;
    let r = mat3(fx.f32("rot.R", &[Some(3), Some(3)])?.1);
    let rotated_grid: Vec<_> = grid
        .iter()
        .map(|g| crate::grids::GridRotation {
            angles: g.angles,
            matrix: r * g.matrix,
        })
        .collect();
    let fw_rot = RotationHead::grid_wigners(&calc, &rotated_grid)?;
    for prefix in ["", "rot."] {
        let (xs, x) = fx.f32(&format!("{prefix}in.x"), &[None, Some(f_in), Some(25)])?;
        let b = xs[0];
        let mut coeffs = Vec::new();
        let mut logits = Vec::new();
        let mut logits_rot = Vec::new();
        for q in x.chunks_exact(f_in * 25) {
            let c = head.so3_coefficients(q)?;
            logits.extend(RotationHead::logits(&c, &fw));
            logits_rot.extend(RotationHead::logits(&c, &fw_rot));
            coeffs.extend(c);
        }
        out.push(compare(
            &format!("{prefix}out.so3_coeffs"),
            &coeffs,
            fx.f32(
                &format!("{prefix}out.so3_coeffs"),
                &[Some(b), Some(SO3_COEFFS)],
            )?
            .1,
            TOL,
        ));
        out.push(compare(
            &format!("{prefix}out.logits"),
            &logits,
            fx.f32(&format!("{prefix}out.logits"), &[Some(b), Some(grid.len())])?
                .1,
            TOL_WIGNER,
        ));
        if prefix == "rot." {
            out.push(compare(
                "rot.out.logits_on_rotated_grid",
                &logits_rot,
                fx.f32(
                    "rot.out.logits_on_rotated_grid",
                    &[Some(b), Some(grid.len())],
                )?
                .1,
                TOL_WIGNER,
            ));
        }
    }
    let _ = flat_wigner;
    Ok(out)
}

fn check_pool_upsample(fx: &FixtureFile) -> Result<Vec<Comparison>> {
    let mut out = Vec::new();
    let (xs, _) = fx.f32("in.x", &[None, None, None])?;
    let (n, nc, c) = (xs[0], xs[1], xs[2]);
    let lmax = (nc as f64).sqrt() as usize - 1;
    if num_coefficients(lmax) != nc {
        return Err(PolicyError::ShapeMismatch {
            name: "in.x".into(),
            expected: vec![n, num_coefficients(lmax), c],
            got: xs.to_vec(),
        });
    }
    for prefix in ["", "rot."] {
        // Inputs not stored under rot.in are unchanged (fixtures README, "Key prefixes").
        let pos = vec3s_f32(fx.f32(&format!("{prefix}in.pos"), &[Some(n), Some(3)])?.1);
        let x = fx
            .f32(&format!("{prefix}in.x"), &[Some(n), Some(nc), Some(c)])?
            .1;
        let m = n.div_ceil(4);
        let centres = farthest_point_sampling(&pos, m)?;
        if prefix.is_empty() {
            out.push(compare_indices(
                "in.centres",
                &centres,
                fx.i64("in.centres", &[Some(m)])?.1,
            ));
        }
        let centre_pos: Vec<[f32; 3]> = centres.iter().map(|&i| pos[i]).collect();
        let neighbours = knn(&pos, &centre_pos, 16)?;
        if prefix.is_empty() {
            let flat: Vec<usize> = neighbours.iter().flatten().copied().collect();
            out.push(compare_indices(
                "in.neighbours",
                &flat,
                fx.i64("in.neighbours", &[Some(m), Some(16)])?.1,
            ));
        }
        let pooled = coefficient_max_pool(x, n, lmax, c, &neighbours)?;
        out.push(compare_f32(
            &format!("{prefix}out.pooled"),
            &pooled,
            fx.f32(
                &format!("{prefix}out.pooled"),
                &[Some(m), Some(nc), Some(c)],
            )?
            .1,
            TOL,
        ));
        let up_nb = knn(&centre_pos, &pos, 3)?;
        if prefix.is_empty() {
            let flat: Vec<usize> = up_nb.iter().flatten().copied().collect();
            out.push(compare_indices(
                "in.up_neighbours",
                &flat,
                fx.i64("in.up_neighbours", &[Some(n), Some(3)])?.1,
            ));
        }
        let w = upsample_weights(&pos, &centre_pos, &up_nb, UpsampleDistance::L1)?;
        let wf: Vec<f32> = w.iter().flatten().copied().collect();
        out.push(compare_f32(
            &format!("{prefix}out.up_weights"),
            &wf,
            fx.f32(&format!("{prefix}out.up_weights"), &[Some(n), Some(3)])?
                .1,
            TOL,
        ));
        let up = upsample(&pooled, m, nc * c, &up_nb, &w)?;
        out.push(compare_f32(
            &format!("{prefix}out.upsampled"),
            &up,
            fx.f32(
                &format!("{prefix}out.upsampled"),
                &[Some(n), Some(nc), Some(c)],
            )?
            .1,
            TOL,
        ));
    }
    Ok(out)
}

fn check_linear_norm_rbf(fx: &FixtureFile) -> Result<Vec<Comparison>> {
    use crate::layers::{
        smooth_leaky_relu, FilmLinear, GaussianRbf, RadialMlp, RmsNormSh, So3Linear,
    };
    let mut out = Vec::new();
    let w = fx.weights();
    let p = w.scope("param.");
    let so3_linear = So3Linear::load(&p.sub("so3_linear"))?;
    let rms = RmsNormSh::load_any(&p.sub("rms_norm"))?;
    let film_cin = fx.f32("in.film_linear.x", &[None, None, None])?.0[2];
    let film_cout = fx.f32("out.film_linear.y", &[None, None, None])?.0[2];
    let film = FilmLinear::load(&p.sub("film_linear"), 3, film_cin, film_cout)?;
    let cutoff = |name: &str| -> Result<f64> {
        fx.sidecar
            .pointer(&format!("/submodules/{name}/args/cutoff"))
            .and_then(|v| v.as_f64())
            .ok_or_else(|| PolicyError::Sidecar {
                path: fx.path.with_extension("json"),
                message: format!("submodules.{name}.args.cutoff missing"),
            })
    };
    let rbf = GaussianRbf::load(&p.sub("rbf"), cutoff("rbf")?)?;
    let rbf_field = GaussianRbf::load(&p.sub("rbf_field"), cutoff("rbf_field")?)?;
    let radial = RadialMlp::load(&p.sub("radial_mlp"))?;

    // The degree-balance buffer of the norm.
    let bdw: Vec<f64> = (0..num_coefficients(rms.lmax))
        .map(|i| rms.balance_weight(i))
        .collect();
    out.push(compare(
        "buf.rms_norm.balance_degree_weight",
        &bdw,
        fx.f32_any("buf.rms_norm.balance_degree_weight")?.1,
        TOL,
    ));
    for prefix in ["", "rot."] {
        let x = fx.f32_any(&format!("{prefix}in.so3_linear.x"))?.1;
        out.push(compare_f32(
            &format!("{prefix}out.so3_linear.y"),
            &so3_linear.forward(x)?,
            fx.f32_any(&format!("{prefix}out.so3_linear.y"))?.1,
            TOL,
        ));
        let x = fx.f32_any(&format!("{prefix}in.rms_norm.x"))?.1;
        out.push(compare_f32(
            &format!("{prefix}out.rms_norm.y"),
            &rms.forward(x)?,
            fx.f32_any(&format!("{prefix}out.rms_norm.y"))?.1,
            TOL,
        ));
        let x = fx.f32_any(&format!("{prefix}in.film_linear.x"))?.1;
        let cond = fx.f32_any("in.film_linear.condition")?.1;
        out.push(compare_f32(
            &format!("{prefix}out.film_linear.y"),
            &film.forward(x, cond)?,
            fx.f32_any(&format!("{prefix}out.film_linear.y"))?.1,
            TOL,
        ));
    }
    let d = fx.f32_any("in.rbf.dist")?.1;
    let y = rbf.forward(d);
    out.push(compare_f32(
        "out.rbf.y",
        &y,
        fx.f32_any("out.rbf.y")?.1,
        TOL,
    ));
    out.push(compare_f32(
        "out.radial_mlp.y",
        &radial.forward(fx.f32_any("out.rbf.y")?.1)?,
        fx.f32_any("out.radial_mlp.y")?.1,
        TOL,
    ));
    let d = fx.f32_any("in.rbf_field.dist")?.1;
    out.push(compare_f32(
        "out.rbf_field.y",
        &rbf_field.forward(d),
        fx.f32_any("out.rbf_field.y")?.1,
        TOL,
    ));
    let x = fx.f32_any("in.smooth_leaky_relu.x")?.1;
    let y: Vec<f32> = x.iter().map(|v| smooth_leaky_relu(*v, 0.2)).collect();
    out.push(compare_f32(
        "out.smooth_leaky_relu.y",
        &y,
        fx.f32_any("out.smooth_leaky_relu.y")?.1,
        TOL,
    ));
    Ok(out)
}

/// A sidecar integer at a JSON pointer.
fn sidecar_usize(fx: &FixtureFile, pointer: &str) -> Result<usize> {
    fx.sidecar
        .pointer(pointer)
        .and_then(|v| v.as_u64())
        .map(|v| v as usize)
        .ok_or_else(|| PolicyError::Sidecar {
            path: fx.path.with_extension("json"),
            message: format!("{pointer} missing or not an integer"),
        })
}

fn check_so2_conv(fx: &FixtureFile) -> Result<Vec<Comparison>> {
    use crate::layers::separable_s2_activation;
    use crate::so2_conv::{CoefficientMapping, EdgeWigners, So2Conv};
    let mut out = Vec::new();
    let c1 = "/constructor/so2_conv_1";
    let lmax = sidecar_usize(fx, &format!("{c1}/lmax_list/0"))?;
    let mmax = sidecar_usize(fx, &format!("{c1}/mmax_list/0"))?;
    let cin = sidecar_usize(fx, &format!("{c1}/sphere_channels"))?;
    let hidden = sidecar_usize(fx, &format!("{c1}/m_output_channels"))?;
    let extra = sidecar_usize(fx, &format!("{c1}/extra_m0_output_channels"))?;
    let cout2 = sidecar_usize(fx, "/constructor/so2_conv_2/m_output_channels")?;
    let map = CoefficientMapping::new(lmax, mmax)?;
    let w = fx.weights();
    let p = w.scope("param.");
    let conv1 = So2Conv::load(&p.sub("so2_conv_1"), &map, cin, hidden, extra, true)?;
    let conv2 = So2Conv::load(&p.sub("so2_conv_2"), &map, hidden, cout2, 0, false)?;
    let grid = S2Grid::reference(lmax, mmax)?;
    let calc = WignerCalculator::new(lmax)?;
    let nr = map.len();
    let k = num_coefficients(lmax);

    // The mapping tables.
    let mm = map.m_major();
    let mut to_m = vec![0.0f64; nr * nr];
    for (row, &col) in mm.iter().enumerate() {
        to_m[row * nr + col] = 1.0;
    }
    out.push(compare(
        "buf.mapping.to_m",
        &to_m,
        fx.f32("buf.mapping.to_m", &[Some(nr), Some(nr)])?.1,
        0.0,
    ));
    out.push(compare_indices(
        "buf.mapping.reduced_coef_idx",
        &map.reduced,
        fx.i64("buf.mapping.reduced_coef_idx", &[Some(nr)])?.1,
    ));
    // Rescaled inside the diagonal blocks of degree > mmax (elsewhere D is zero anyway).
    let mut rescale = vec![1.0f64; k * nr];
    for i in 0..k {
        for (r, &j) in map.reduced.iter().enumerate() {
            if crate::layers::degree_of(i) == crate::layers::degree_of(j) {
                rescale[i * nr + r] = f64::from(map.rotate_inv_rescale(i));
            }
        }
    }
    out.push(compare(
        "buf.mapping.rotate_inv_rescale",
        &rescale,
        fx.f32("buf.mapping.rotate_inv_rescale", &[Some(k), Some(nr)])?
            .1,
        TOL,
    ));

    let x_edge = fx.f32_any("in.x_edge")?.1;
    for prefix in ["", "rot."] {
        let ev = vec3s_f32(fx.f32(&format!("{prefix}in.edge_vec"), &[None, Some(3)])?.1);
        let ne = ev.len();
        let wig = EdgeWigners::new(&calc, lmax, &ev)?;
        if prefix.is_empty() {
            out.push(compare_f32(
                "out.wigner",
                &wig.d,
                fx.f32("out.wigner", &[Some(ne), Some(k), Some(k)])?.1,
                TOL_WIGNER,
            ));
        }
        let x = fx
            .f32(&format!("{prefix}in.x"), &[Some(ne), Some(k), Some(cin)])?
            .1;
        let x_rot = wig.rotate(&map, x, cin)?;
        let (y1, x0_extra) = conv1.forward(&x_rot, Some(x_edge))?;
        let gating: Vec<f32> = x0_extra
            .chunks_exact(extra)
            .flat_map(|r| r[extra - hidden..].iter().copied())
            .collect();
        let act = separable_s2_activation(&grid, &gating, &y1, hidden)?;
        let (y2, _) = conv2.forward(&act, None)?;
        let y = wig.rotate_back(&map, &y2, cout2)?;
        let back1 = wig.rotate_back(&map, &y1, hidden)?;
        if prefix.is_empty() {
            for (key, v) in [
                ("out.x_rot", &x_rot),
                ("out.conv1", &y1),
                ("out.s2act", &act),
                ("out.conv2", &y2),
            ] {
                out.push(compare_f32(key, v, fx.f32_any(key)?.1, TOL_WIGNER));
            }
        }
        for (key, v) in [
            ("out.x0_extra", &x0_extra),
            ("out.conv1_back", &back1),
            ("out.y", &y),
        ] {
            let key = format!("{prefix}{key}");
            out.push(compare_f32(&key, v, fx.f32_any(&key)?.1, TOL_WIGNER));
        }
    }
    Ok(out)
}

/// A sidecar float at a JSON pointer.
fn sidecar_f64(fx: &FixtureFile, pointer: &str) -> Result<f64> {
    fx.sidecar
        .pointer(pointer)
        .and_then(|v| v.as_f64())
        .ok_or_else(|| PolicyError::Sidecar {
            path: fx.path.with_extension("json"),
            message: format!("{pointer} missing or not a number"),
        })
}

/// The attention sizes from a constructor record (`output_channels` may be overridden).
fn attention_config(
    fx: &FixtureFile,
    ctor: &str,
    output_channels: Option<usize>,
) -> Result<crate::attention::AttentionConfig> {
    let g = |k: &str| sidecar_usize(fx, &format!("{ctor}/{k}"));
    Ok(crate::attention::AttentionConfig {
        lmax: g("lmax_list/0")?,
        mmax: g("mmax_list/0")?,
        sphere_channels: g("sphere_channels")?,
        hidden_channels: g("hidden_channels").or_else(|_| g("attn_hidden_channels"))?,
        num_heads: g("num_heads")?,
        alpha_channels: g("attn_alpha_channels")?,
        value_channels: g("attn_value_channels")?,
        output_channels: match output_channels {
            Some(c) => c,
            None => g("output_channels")?,
        },
    })
}

fn indices(fx: &FixtureFile, key: &str) -> Result<Vec<usize>> {
    let (_, v) = fx.i64(key, &[None])?;
    v.iter()
        .map(|&i| {
            usize::try_from(i).map_err(|_| PolicyError::IndexOutOfRange {
                name: key.to_string(),
                value: i,
                len: 0,
            })
        })
        .collect()
}

/// The fixture's graph (given edge vectors and features) for the plain and the moved run,
/// plus a check of our radial basis against `in.edge_attr`.
fn fixture_edges(
    fx: &FixtureFile,
    calc: &WignerCalculator,
    lmax: usize,
    prefix: &str,
    out: &mut Vec<Comparison>,
) -> Result<crate::attention::EdgeSet> {
    use crate::attention::EdgeSet;
    use crate::layers::GaussianRbf;
    let src = indices(fx, "in.edge_src")?;
    let dst = indices(fx, "in.edge_dst")?;
    let ne = src.len();
    let ev = vec3s_f32(
        fx.f32(&format!("{prefix}in.edge_vec"), &[Some(ne), Some(3)])?
            .1,
    );
    let attr = fx
        .f32(&format!("{prefix}in.edge_attr"), &[Some(ne), None])?
        .1;
    let edges = EdgeSet::from_parts(calc, lmax, src, dst, ev, attr.to_vec())?;
    let w = fx.weights();
    let rbf = GaussianRbf::load(
        &w.scope("param.").sub("distance_expansion"),
        sidecar_f64(fx, "/distance_expansion/cutoff")?,
    )?;
    out.push(compare_f32(
        &format!("{prefix}in.edge_attr (ours from |edge_vec|)"),
        &rbf.forward(&edges.dist),
        attr,
        TOL,
    ));
    if prefix.is_empty() {
        let pos = vec3s_f32(fx.f32("in.pos", &[None, Some(3)])?.1);
        let mut ev = Vec::with_capacity(ne);
        for (&s, &d) in edges.src.iter().zip(&edges.dst) {
            let (Some(a), Some(b)) = (pos.get(s), pos.get(d)) else {
                return Err(PolicyError::IndexOutOfRange {
                    name: "in.edge_src/in.edge_dst".into(),
                    value: s.max(d) as i64,
                    len: pos.len(),
                });
            };
            ev.extend([a[0] - b[0], a[1] - b[1], a[2] - b[2]]);
        }
        out.push(compare_f32(
            "in.edge_vec (ours from in.pos)",
            &ev,
            fx.f32_any("in.edge_vec")?.1,
            TOL,
        ));
        let k = num_coefficients(lmax);
        out.push(compare_f32(
            "buf.wigner",
            &edges.wigners.d,
            fx.f32("buf.wigner", &[Some(ne), Some(k), Some(k)])?.1,
            TOL_WIGNER,
        ));
    }
    Ok(edges)
}

fn check_graph_attention(fx: &FixtureFile) -> Result<Vec<Comparison>> {
    use crate::attention::GraphAttention;
    let mut out = Vec::new();
    let cfg = attention_config(fx, "/constructor", None)?;
    let w = fx.weights();
    let mut ga = GraphAttention::load(&w.scope("param."), cfg)?;
    let calc = WignerCalculator::new(cfg.lmax)?;
    for prefix in ["", "rot."] {
        let edges = fixture_edges(fx, &calc, cfg.lmax, prefix, &mut out)?;
        let x = fx.f32_any(&format!("{prefix}in.x"))?.1;
        let y = ga.forward(x, x, &edges)?;
        let key = format!("{prefix}out.y");
        out.push(compare_f32(&key, &y, fx.f32_any(&key)?.1, TOL_WIGNER));
        // The field heads' path onto zero destinations (source half of the messages only)
        // against the general path with zero destination features.
        let zeros = vec![0.0f32; x.len()];
        let general = ga.forward(x, &zeros, &edges)?;
        ga.prepare_zero_destinations()?;
        let nd = x.len() / (num_coefficients(cfg.lmax) * cfg.sphere_channels).max(1);
        let narrow = ga.forward_zero_destinations(x, nd, &edges)?;
        out.push(compare_f32(
            &format!("{prefix}zero destinations (ours: source-only vs general)"),
            &narrow,
            &general,
            TOL,
        ));
    }
    Ok(out)
}

/// TransBlock sizes from a constructor record.
fn transblock_config(fx: &FixtureFile, ctor: &str) -> Result<crate::transblock::TransBlockConfig> {
    let attn = attention_config(
        fx,
        ctor,
        Some(sidecar_usize(fx, &format!("{ctor}/sphere_channels"))?),
    )?;
    let film = fx
        .sidecar
        .pointer(&format!("{ctor}/film_dim"))
        .and_then(|v| v.as_u64())
        .unwrap_or(0)
        > 0;
    // The fixtures come from the reference code, whose FiLM is the hypernetwork.
    let film = film.then_some(crate::transblock::FilmKind::Hypernetwork);
    Ok(crate::transblock::TransBlockConfig {
        attn,
        ffn_hidden_channels: sidecar_usize(fx, &format!("{ctor}/ffn_hidden_channels"))?,
        output_channels: sidecar_usize(fx, &format!("{ctor}/output_channels"))?,
        film,
    })
}

fn check_transblock(fx: &FixtureFile) -> Result<Vec<Comparison>> {
    use crate::transblock::TransBlock;
    let mut out = Vec::new();
    let cfg = transblock_config(fx, "/constructor")?;
    let w = fx.weights();
    let block = TransBlock::load(&w.scope("param."), cfg)?;
    let calc = WignerCalculator::new(cfg.attn.lmax)?;
    let cond = fx.f32_any("in.condition")?.1;
    for prefix in ["", "rot."] {
        let edges = fixture_edges(fx, &calc, cfg.attn.lmax, prefix, &mut out)?;
        let x = fx.f32_any(&format!("{prefix}in.x"))?.1;
        let y = block.forward(x, x, &edges, Some(cond))?;
        let key = format!("{prefix}out.y");
        out.push(compare_f32(&key, &y, fx.f32_any(&key)?.1, TOL_WIGNER));
    }
    Ok(out)
}

fn check_language_encoder(fx: &FixtureFile) -> Result<Vec<Comparison>> {
    use crate::language::{positional_encoding, InstructionEncoder};
    let mut out = Vec::new();
    let heads = sidecar_usize(fx, "/constructor/heads")?;
    let dim_head = sidecar_usize(fx, "/constructor/dim_head")?;
    let w = fx.weights();
    let enc = InstructionEncoder::load(&w.scope("param."), heads, dim_head)?;
    let (shape, instr) = fx.f32("in.instruction", &[None, None, Some(enc.token_dim())])?;
    let (b, t) = (shape[0], shape[1]);
    out.push(compare_f32(
        "buf.posemb",
        &positional_encoding(t + 1, enc.dim),
        fx.f32("buf.posemb", &[Some(t + 1), Some(enc.dim)])?.1,
        TOL,
    ));
    out.push(compare_f32(
        "mid.tokens_in",
        &enc.tokens_in(instr, b)?,
        fx.f32("mid.tokens_in", &[Some(b), Some(t + 1), Some(enc.dim)])?
            .1,
        TOL,
    ));
    out.push(compare_f32(
        "out.tokens",
        &enc.forward(instr, b)?,
        fx.f32("out.tokens", &[Some(b), Some(t + 1), Some(enc.dim)])?
            .1,
        TOL,
    ));
    out.push(compare_f32(
        "out.condition",
        &enc.condition(instr, b)?,
        fx.f32("out.condition", &[Some(b), Some(enc.dim)])?.1,
        TOL,
    ));
    Ok(out)
}

/// Field-head sizes from the `EquFieldUnet` constructor record.
fn field_heads_config(fx: &FixtureFile) -> Result<crate::heads::FieldHeadsConfig> {
    let g = |k: &str| sidecar_usize(fx, &format!("/constructor/EquFieldUnet/{k}"));
    Ok(crate::heads::FieldHeadsConfig {
        field_channels: g("field_nn_c")?,
        attn_hidden_channels: g("attn_hidden_channels/1")?,
        num_heads: g("num_heads")?,
        alpha_channels: g("attn_alpha_channels/1")?,
        value_channels: g("attn_value_channels/1")?,
        ffn_hidden_channels: g("ffn_hidden_channels/1")?,
        node_lmax: g("lmax_list/0")?,
    })
}

fn check_query_heads(fx: &FixtureFile) -> Result<Vec<Comparison>> {
    use crate::heads::FieldHeads;
    let mut out = Vec::new();
    let cfg = field_heads_config(fx)?;
    let w = fx.weights();
    let heads = FieldHeads::load(&w.scope("param."), cfg, 1)?;
    let r = mat3(fx.f32("rot.R", &[Some(3), Some(3)])?.1);
    for prefix in ["", "rot."] {
        let pos = vec3s_f32(
            fx.f32(&format!("{prefix}in.node_coord"), &[None, Some(3)])?
                .1,
        );
        let emb = fx.f32_any(&format!("{prefix}in.node_embedding"))?.1;
        let tq = vec3s_f32(
            fx.f32(
                &format!("{prefix}in.trans_queries"),
                &[Some(1), None, Some(3)],
            )?
            .1,
        );
        let rq = vec3s_f32(
            fx.f32(
                &format!("{prefix}in.rot_query"),
                &[Some(1), Some(1), Some(3)],
            )?
            .1,
        );
        let Some(&rq) = rq.first() else {
            return Err(PolicyError::ShapeMismatch {
                name: format!("{prefix}in.rot_query"),
                expected: vec![1, 1, 3],
                got: vec![0],
            });
        };
        if prefix.is_empty() {
            let (src, dst) = FieldHeads::trans_edges(&pos, &tq)?;
            out.push(compare_indices(
                "mid.trans_edge_src",
                &src,
                fx.i64("mid.trans_edge_src", &[None])?.1,
            ));
            out.push(compare_indices(
                "mid.trans_edge_dst",
                &dst,
                fx.i64("mid.trans_edge_dst", &[None])?.1,
            ));
            let (src, dst) = FieldHeads::rot_edges(&pos, &[rq])?;
            out.push(compare_indices(
                "mid.rot_edge_src",
                &src,
                fx.i64("mid.rot_edge_src", &[None])?.1,
            ));
            out.push(compare_indices(
                "mid.rot_edge_dst",
                &dst,
                fx.i64("mid.rot_edge_dst", &[None])?.1,
            ));
        }
        let key = format!("{prefix}out.trans_logits");
        out.push(compare_f32(
            &key,
            &heads.trans_logits(emb, &pos, &tq)?,
            fx.f32_any(&key)?.1,
            TOL_WIGNER,
        ));
        let q = heads.rot_query(emb, &pos, rq)?;
        if prefix.is_empty() {
            out.push(compare_f32(
                "mid.rot_query_embedding",
                &q.embedding,
                fx.f32_any("mid.rot_query_embedding")?.1,
                TOL_WIGNER,
            ));
            out.push(compare(
                "mid.so3_coeffs",
                &q.so3_coeffs,
                fx.f32_any("mid.so3_coeffs")?.1,
                TOL_WIGNER,
            ));
        }
        let key = format!("{prefix}out.open_logit");
        out.push(compare_f32(
            &key,
            &[q.open_logit],
            fx.f32_any(&key)?.1,
            TOL_WIGNER,
        ));
        let key = format!("{prefix}out.rot_logits");
        out.push(compare(
            &key,
            &q.rot_logits,
            fx.f32_any(&key)?.1,
            TOL_WIGNER,
        ));
        if !prefix.is_empty() {
            let rotated: Vec<_> = heads
                .grid()
                .iter()
                .map(|g| crate::grids::GridRotation {
                    angles: g.angles,
                    matrix: r * g.matrix,
                })
                .collect();
            let key = "rot.out.rot_logits_on_rotated_grid";
            out.push(compare(
                key,
                &heads.logits_on(&q.so3_coeffs, &rotated)?,
                fx.f32_any(key)?.1,
                TOL_WIGNER,
            ));
        }
    }
    Ok(out)
}

/// Tolerance of the whole model (fixtures README: 1e-4 on logits, 1e-4·(1+|ref|) on
/// intermediates).
pub const TOL_MODEL: f64 = 1e-4;

/// Groups a recorded `[2, E]` (query, source) kNN record into per-query lists.
fn knn_lists(fx: &FixtureFile, key: &str) -> Result<Vec<Vec<usize>>> {
    let (shape, v) = fx.i64(key, &[Some(2), None])?;
    let e = shape[1];
    let mut out: Vec<Vec<usize>> = Vec::new();
    for j in 0..e {
        let (q, s) = (v[j], v[e + j]);
        let (Ok(q), Ok(s)) = (usize::try_from(q), usize::try_from(s)) else {
            return Err(PolicyError::IndexOutOfRange {
                name: key.to_string(),
                value: q.min(s),
                len: 0,
            });
        };
        if q >= out.len() {
            out.resize(q + 1, Vec::new());
        }
        out[q].push(s);
    }
    Ok(out)
}

/// The recorded choices of one U-net block of the whole-model fixture.
fn recorded_indices(
    fx: &FixtureFile,
    block: &str,
    scale: f64,
) -> Result<crate::model::BlockIndices> {
    let mut idx = crate::model::BlockIndices::default();
    if scale < 1.0 {
        let mut fps = indices(fx, &format!("mid.{block}.fps0"))?;
        fps.sort_unstable();
        fps.dedup();
        idx.fps = Some(fps);
        idx.pool_knn = Some(knn_lists(fx, &format!("mid.{block}.knn0"))?);
    } else if scale > 1.0 {
        idx.up_knn = Some(knn_lists(fx, &format!("mid.{block}.knn0"))?);
    }
    idx.graph = Some((
        indices(fx, &format!("mid.{block}.edge_src"))?,
        indices(fx, &format!("mid.{block}.edge_dst"))?,
    ));
    Ok(idx)
}

fn check_whole_model(fx: &FixtureFile) -> Result<Vec<Comparison>> {
    use crate::model::{EquFieldUnet, GripperState, ModelConfig};
    let mut out = Vec::new();
    let ctor = fx
        .sidecar
        .pointer("/constructor/EquFieldUnet")
        .ok_or_else(|| PolicyError::Sidecar {
            path: fx.path.with_extension("json"),
            message: "constructor.EquFieldUnet missing".into(),
        })?;
    let cfg = ModelConfig::from_constructor(ctor)?;
    let w = fx.weights();
    let model = EquFieldUnet::load(&w.scope("param."), cfg.clone())?;
    let names = model.block_names();
    let scales: Vec<f64> = cfg
        .pool_ratio
        .iter()
        .copied()
        .chain(std::iter::once(cfg.pool_ratio[cfg.n_scales() - 1]))
        .chain(cfg.pool_ratio.iter().rev().map(|r| 1.0 / r))
        .collect();
    let r = mat3(fx.f32("rot.R", &[Some(3), Some(3)])?.1);
    let rgb = vec3s_f32(fx.f32("in.rgb", &[Some(1), None, Some(3)])?.1);
    let instr = fx.f32("in.instruction", &[Some(1), None, None])?.1;
    for prefix in ["", "rot."] {
        let xyz = vec3s_f32(
            fx.f32(&format!("{prefix}in.xyz"), &[Some(1), None, Some(3)])?
                .1,
        );
        let g = fx
            .f32(&format!("{prefix}in.curr_gripper"), &[Some(1), Some(8)])?
            .1;
        let gripper = GripperState {
            position: [g[0], g[1], g[2]],
            quaternion: [g[3], g[4], g[5], g[6]],
            open: g[7],
        };
        let eps = vec3s_f32(
            fx.f32(&format!("{prefix}in.gripper_pos_eps"), &[None, Some(3)])?
                .1,
        );
        let tq = vec3s_f32(
            fx.f32(
                &format!("{prefix}in.trans_queries"),
                &[Some(1), None, Some(3)],
            )?
            .1,
        );
        let rq = vec3s_f32(
            fx.f32(
                &format!("{prefix}in.rot_query"),
                &[Some(1), Some(1), Some(3)],
            )?
            .1,
        );
        let Some(&rq) = rq.first() else {
            return Err(PolicyError::ShapeMismatch {
                name: format!("{prefix}in.rot_query"),
                expected: vec![1, 1, 3],
                got: vec![0],
            });
        };
        // The plain run follows the recorded choices (the near-coincident gripper points
        // make some of them fragile); the free run's choices are compared with them.
        let overrides = if prefix.is_empty() {
            names
                .iter()
                .zip(&scales)
                .map(|(n, s)| Ok((n.clone(), recorded_indices(fx, n, *s)?)))
                .collect::<Result<Vec<_>>>()?
        } else {
            Vec::new()
        };
        let enc = model.encode(&xyz, &rgb, &gripper, &eps, instr, &overrides)?;
        if prefix.is_empty() {
            let free = model.encode(&xyz, &rgb, &gripper, &eps, instr, &[])?;
            let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
            out.push(compare_f32(
                "mid.xyz_effective",
                &flat(&enc.xyz),
                fx.f32_any("mid.xyz_effective")?.1,
                0.0,
            ));
            out.push(compare_f32(
                "mid.condition",
                &enc.condition,
                fx.f32_any("mid.condition")?.1,
                TOL,
            ));
            for (t, (name, rec)) in free.blocks.iter().zip(&overrides) {
                let mismatch = |a: &Option<Vec<Vec<usize>>>, b: &Option<Vec<Vec<usize>>>| {
                    let a: Vec<usize> = a.iter().flatten().flatten().copied().collect();
                    let b: Vec<i64> = b.iter().flatten().flatten().map(|&v| v as i64).collect();
                    (a, b)
                };
                let (a, b) = mismatch(&t.indices.pool_knn, &rec.pool_knn);
                let (c, d) = mismatch(&t.indices.up_knn, &rec.up_knn);
                let fa: Vec<usize> = t.indices.fps.iter().flatten().copied().collect();
                let fb: Vec<i64> = rec.fps.iter().flatten().map(|&v| v as i64).collect();
                let (ga, gb) = match (&t.indices.graph, &rec.graph) {
                    (Some((s1, d1)), Some((s2, d2))) => (
                        s1.iter().chain(d1).copied().collect::<Vec<_>>(),
                        s2.iter().chain(d2).map(|&v| v as i64).collect::<Vec<_>>(),
                    ),
                    _ => (Vec::new(), vec![-1]),
                };
                let all_a: Vec<usize> = fa.into_iter().chain(a).chain(c).chain(ga).collect();
                let all_b: Vec<i64> = fb.into_iter().chain(b).chain(d).chain(gb).collect();
                let cmp = compare_indices(
                    &format!("free run {name} choices (fps, knn, edges)"),
                    &all_a,
                    &all_b,
                );
                out.push(cmp);
            }
            for (t, next) in enc.blocks.iter().zip(enc.blocks.iter().skip(1)) {
                if let Some(after) = &t.after_skip {
                    let key = format!("mid.{}.in_embedding", next.name);
                    out.push(compare_f32(&key, after, fx.f32_any(&key)?.1, TOL_MODEL));
                }
            }
            for t in &enc.blocks {
                let key = format!("mid.{}.out_embedding", t.name);
                out.push(compare_f32(
                    &key,
                    &t.embedding,
                    fx.f32_any(&key)?.1,
                    TOL_MODEL,
                ));
                let key = format!("mid.{}.out_coord", t.name);
                out.push(compare_f32(&key, &flat(&t.coord), fx.f32_any(&key)?.1, 0.0));
            }
        }
        let key = format!("{prefix}out.unet_embedding");
        out.push(compare_f32(
            &key,
            &enc.embedding,
            fx.f32_any(&key)?.1,
            TOL_MODEL,
        ));
        let q = model.query(&enc, &tq, rq)?;
        let key = format!("{prefix}out.trans_logits");
        out.push(compare_f32(
            &key,
            &q.trans_logits,
            fx.f32_any(&key)?.1,
            TOL_MODEL,
        ));
        let key = format!("{prefix}out.open_logit");
        out.push(compare_f32(
            &key,
            &[q.rot.open_logit],
            fx.f32_any(&key)?.1,
            TOL_MODEL,
        ));
        let key = format!("{prefix}out.rot_logits");
        out.push(compare(
            &key,
            &q.rot.rot_logits,
            fx.f32_any(&key)?.1,
            TOL_MODEL,
        ));
        if prefix.is_empty() {
            out.push(compare_f32(
                "mid.rot_query_embedding",
                &q.rot.embedding,
                fx.f32_any("mid.rot_query_embedding")?.1,
                TOL_MODEL,
            ));
            out.push(compare(
                "mid.so3_coeffs",
                &q.rot.so3_coeffs,
                fx.f32_any("mid.so3_coeffs")?.1,
                TOL_MODEL,
            ));
        } else {
            let rotated: Vec<_> = model
                .heads()
                .grid()
                .iter()
                .map(|g| crate::grids::GridRotation {
                    angles: g.angles,
                    matrix: r * g.matrix,
                })
                .collect();
            let key = "rot.out.rot_logits_on_rotated_grid";
            out.push(compare(
                key,
                &model.heads().logits_on(&q.rot.so3_coeffs, &rotated)?,
                fx.f32_any(key)?.1,
                TOL_MODEL,
            ));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The `graph_attention` fixture's layer, edges (64 nodes, 960 edges) and input.
    fn fixture_attention() -> (
        crate::attention::GraphAttention,
        crate::attention::EdgeSet,
        Vec<f32>,
    ) {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/fixtures/graph_attention.safetensors"
        );
        let fx = FixtureFile::load(Path::new(path)).unwrap();
        let cfg = attention_config(&fx, "/constructor", None).unwrap();
        let w = fx.weights();
        let ga = crate::attention::GraphAttention::load(&w.scope("param."), cfg).unwrap();
        let calc = WignerCalculator::new(cfg.lmax).unwrap();
        let edges = fixture_edges(&fx, &calc, cfg.lmax, "", &mut Vec::new()).unwrap();
        let x = fx.f32_any("in.x").unwrap().1.to_vec();
        (ga, edges, x)
    }

    #[test]
    fn threaded_attention_equals_one_thread_and_refuses_bad_destinations() {
        let (mut ga, mut edges, x) = fixture_attention();
        let x = x.as_slice();
        let one = ga.forward(x, x, &edges).unwrap();
        ga.set_threads(2);
        assert_eq!(ga.forward(x, x, &edges).unwrap(), one, "bit for bit");
        // Destinations past the 64 nodes from the second chunk on (edge 520 starts it), still
        // in ascending order: an error naming the edges, not a panic while the rows of the
        // aggregate are handed out to the threads.
        for d in edges.dst.iter_mut().skip(520) {
            *d = 70;
        }
        let err = ga.forward(x, x, &edges).unwrap_err();
        assert!(err.to_string().contains("edge_dst"), "{err}");
    }

    #[test]
    fn one_destination_split_over_threads_equals_one_thread() {
        // The fixture's 960 edges all into one destination (as the rotation head's query),
        // then into destinations out of order: one chunk either way, whose edges the threads
        // split; the values must be those of one thread, bit for bit.
        let (mut ga, mut edges, x) = fixture_attention();
        let x = x.as_slice();
        let layouts: [fn(usize) -> usize; 2] = [|_| 5, |e| (e * 37) % 64];
        for destinations in layouts {
            for (e, d) in edges.dst.iter_mut().enumerate() {
                *d = destinations(e);
            }
            ga.set_threads(1);
            let one = ga.forward(x, x, &edges).unwrap();
            assert!(one.iter().any(|v| *v != 0.0));
            for threads in [2, 3] {
                ga.set_threads(threads);
                assert_eq!(ga.forward(x, x, &edges).unwrap(), one, "{threads} threads");
            }
        }
        // A destination past the nodes is still an error, not a panic in a thread.
        edges.dst[700] = 64;
        ga.set_threads(2);
        let err = ga.forward(x, x, &edges).unwrap_err();
        assert!(err.to_string().contains("edge_src/edge_dst"), "{err}");
    }
}
