//! Reverse-mode automatic differentiation for training the network.
//!
//! The inference layers (`crate::layers`, `attention`, ...) are specialised for speed
//! (transposed and pruned weights, chunked edges, zero destinations) and keep no
//! intermediate values. Training runs a second, plain forward on a [`Tape`]: every operation
//! records its output and a closure that maps the output's gradient onto its inputs'
//! gradients; [`Tape::backward`] runs those closures in reverse. Parameters are read by their
//! state-dict names from a [`Weights`](crate::weights::Weights) store, so the same store
//! serves the inference model, the optimiser and the checkpoints. Tests check every taped
//! layer against its inference twin (same outputs) and against finite differences (same
//! gradients).
//!
//! No library: burn or candle would bring a second tensor stack beside the hand-written
//! inference kernels, and a dozen operations cover the network. Everything is `f32` on the
//! calling thread; products go through [`crate::matmul`].

pub mod attention;
pub mod check;
pub mod ffn;
pub mod language;
pub mod layers;
pub mod model;
mod ops;
pub mod plain_heads;
pub mod points;
pub mod rotation;

pub use ops::Act;

use std::collections::HashMap;
use std::rc::Rc;

use crate::error::{PolicyError, Result};
use crate::weights::Scope;

/// A value recorded on a [`Tape`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Var(usize);

/// Maps the gradient of a node's output onto the gradients of its inputs.
type BackFn = Box<dyn Fn(&Values<'_>, &[f32], &mut Grads)>;

struct Node {
    /// Shared, so that a reshape records its input's values without copying them.
    value: Rc<Vec<f32>>,
    shape: Vec<usize>,
    needs_grad: bool,
    back: Option<Backward>,
}

/// How a node's output gradient reaches its inputs.
enum Backward {
    /// A closure maps it onto the inputs' accumulators.
    Map(BackFn),
    /// The output is its input's values under another shape: the gradient buffer itself
    /// becomes (or is added to) the input's, without a copy.
    PassTo(Var),
}

/// The recorded forward computation.
#[derive(Default)]
pub struct Tape {
    nodes: Vec<Node>,
    /// Parameter leaves by full state-dict key, in first-use order.
    params: Vec<(String, Var)>,
    param_index: HashMap<String, Var>,
}

impl std::fmt::Debug for Tape {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Tape")
            .field("nodes", &self.nodes.len())
            .field("params", &self.params.len())
            .finish()
    }
}

/// Read access to the recorded values during the backward pass.
pub struct Values<'a>(&'a [Node]);

impl Values<'_> {
    /// The forward value of `v`.
    pub fn get(&self, v: Var) -> &[f32] {
        &self.0[v.0].value
    }
}

/// Gradient accumulators of every node (allocated on first use).
pub struct Grads {
    grads: Vec<Option<Vec<f32>>>,
    lens: Vec<usize>,
    needs: Vec<bool>,
}

impl Grads {
    /// The accumulator of `v`, or `None` when nothing upstream of `v` is trained.
    pub fn acc(&mut self, v: Var) -> Option<&mut [f32]> {
        if !self.needs[v.0] {
            return None;
        }
        let len = self.lens[v.0];
        Some(self.grads[v.0].get_or_insert_with(|| vec![0.0; len]))
    }

    /// Whether `v` is trained and has no accumulator yet: a contribution now would be its
    /// first, which [`Grads::add_owned`] takes as it is.
    pub fn starts(&self, v: Var) -> bool {
        self.needs[v.0] && self.grads[v.0].is_none()
    }

    /// Adds `g` into the accumulator of `v` (if it is trained), taking the buffer itself
    /// when `v` has none yet (the same values as adding it to zeros).
    pub fn add_owned(&mut self, v: Var, g: Vec<f32>) {
        if self.needs[v.0] && self.grads[v.0].is_none() {
            debug_assert_eq!(g.len(), self.lens[v.0]);
            self.grads[v.0] = Some(g);
        } else {
            self.add(v, &g);
        }
    }

    /// Adds `g` into the accumulator of `v` (if it is trained); a first contribution is
    /// copied, not added to zeros.
    pub fn add(&mut self, v: Var, g: &[f32]) {
        self.add_iter(v, g.iter().copied());
    }

    /// Adds the values `g` yields (as many as `v` has) into the accumulator of `v`, if it is
    /// trained. A first contribution becomes the accumulator as it is: the same values as
    /// adding it to a zero-filled buffer (0 + x = x), without writing and reading the zeros
    /// (zero-filling was about a tenth of a training step). `g` is not run when `v` is not
    /// trained.
    pub fn add_iter(&mut self, v: Var, g: impl Iterator<Item = f32>) {
        if !self.needs[v.0] {
            return;
        }
        match &mut self.grads[v.0] {
            Some(a) => {
                for (x, y) in a.iter_mut().zip(g) {
                    *x += y;
                }
            }
            slot @ None => {
                let mut fresh = Vec::with_capacity(self.lens[v.0]);
                fresh.extend(g);
                debug_assert_eq!(fresh.len(), self.lens[v.0]);
                // As the zip above would: missing values count as 0, extra ones are dropped.
                fresh.resize(self.lens[v.0], 0.0);
                *slot = Some(fresh);
            }
        }
    }

    /// Adds each of `rows` (all of one width) into columns `at..at + width` of the matching
    /// row of the accumulator of `v` (rows of `stride` values), if `v` is trained. A first
    /// contribution is written with zeros in the other columns instead of being added to a
    /// zero-filled buffer (the same values); the gradient of a column slice or of one side
    /// of a concatenation.
    pub fn add_cols<'g>(
        &mut self,
        v: Var,
        stride: usize,
        at: usize,
        rows: impl Iterator<Item = &'g [f32]>,
    ) {
        if !self.needs[v.0] {
            return;
        }
        match &mut self.grads[v.0] {
            Some(a) => {
                for (dst, r) in a.chunks_exact_mut(stride.max(1)).zip(rows) {
                    for (x, y) in dst[at..at + r.len()].iter_mut().zip(r) {
                        *x += y;
                    }
                }
            }
            slot @ None => {
                let len = self.lens[v.0];
                let mut fresh = Vec::with_capacity(len);
                for r in rows {
                    fresh.resize(fresh.len() + at, 0.0);
                    fresh.extend_from_slice(r);
                    fresh.resize(fresh.len() + stride.saturating_sub(at + r.len()), 0.0);
                }
                // Rows of no width (a slice of no columns) still leave a full accumulator.
                fresh.resize(len, 0.0);
                *slot = Some(fresh);
            }
        }
    }

    /// Whether `v` receives a gradient.
    pub fn wants(&self, v: Var) -> bool {
        self.needs[v.0]
    }
}

/// The gradients of one backward pass.
#[derive(Debug)]
pub struct Gradients {
    grads: Vec<Option<Vec<f32>>>,
}

impl Gradients {
    /// The gradient of `v` (`None`: nothing reached it, i.e. zero). Only leaves (variables
    /// and parameters) keep theirs; interior gradients are consumed by the pass.
    pub fn of(&self, v: Var) -> Option<&[f32]> {
        self.grads.get(v.0).and_then(|g| g.as_deref())
    }
}

impl Tape {
    /// An empty tape.
    pub fn new() -> Self {
        Self::default()
    }

    /// Number of recorded nodes.
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    /// Whether nothing is recorded.
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// The forward value of `v`.
    pub fn value(&self, v: Var) -> &[f32] {
        &self.nodes[v.0].value
    }

    /// The shape of `v`.
    pub fn shape(&self, v: Var) -> &[usize] {
        &self.nodes[v.0].shape
    }

    /// Records a node; it needs a gradient when any of `parents` does.
    fn push(
        &mut self,
        value: Vec<f32>,
        shape: Vec<usize>,
        parents: &[Var],
        back: Option<BackFn>,
    ) -> Var {
        self.push_node(Rc::new(value), shape, parents, back.map(Backward::Map))
    }

    /// Records `a`'s values (shared, not copied) under `shape`; its gradient is handed on
    /// to `a` as it is.
    fn push_reshaped(&mut self, a: Var, shape: Vec<usize>) -> Var {
        let value = Rc::clone(&self.nodes[a.0].value);
        self.push_node(value, shape, &[a], Some(Backward::PassTo(a)))
    }

    fn push_node(
        &mut self,
        value: Rc<Vec<f32>>,
        shape: Vec<usize>,
        parents: &[Var],
        back: Option<Backward>,
    ) -> Var {
        debug_assert_eq!(value.len(), shape.iter().product::<usize>());
        let needs_grad = parents.iter().any(|p| self.nodes[p.0].needs_grad);
        self.nodes.push(Node {
            value,
            shape,
            needs_grad,
            back: if needs_grad { back } else { None },
        });
        Var(self.nodes.len() - 1)
    }

    fn leaf_node(
        &mut self,
        what: &str,
        value: Vec<f32>,
        shape: &[usize],
        grad: bool,
    ) -> Result<Var> {
        check_shape(what, value.len(), shape)?;
        self.nodes.push(Node {
            value: Rc::new(value),
            shape: shape.to_vec(),
            needs_grad: grad,
            back: None,
        });
        Ok(Var(self.nodes.len() - 1))
    }

    /// A value that receives no gradient (data, fixed buffers).
    pub fn constant(&mut self, value: Vec<f32>, shape: &[usize]) -> Result<Var> {
        self.leaf_node("constant", value, shape, false)
    }

    /// A value that receives a gradient (an input under test, a free variable).
    pub fn variable(&mut self, value: Vec<f32>, shape: &[usize]) -> Result<Var> {
        self.leaf_node("variable", value, shape, true)
    }

    /// The trained parameter `name` of `scope`, read once per tape (later uses share it).
    pub fn param(&mut self, scope: &Scope<'_>, name: &str, shape: &[usize]) -> Result<Var> {
        let key = scope.key(name);
        if let Some(&v) = self.param_index.get(&key) {
            check_shape(&key, self.value(v).len(), shape)?;
            if self.shape(v) != shape {
                return Err(PolicyError::ShapeMismatch {
                    name: key,
                    expected: shape.to_vec(),
                    got: self.shape(v).to_vec(),
                });
            }
            return Ok(v);
        }
        let v = self.leaf_node(&key, scope.f32(name, shape)?, shape, true)?;
        self.param_index.insert(key.clone(), v);
        self.params.push((key, v));
        Ok(v)
    }

    /// The parameters read so far, by full key, in first-use order.
    pub fn params(&self) -> &[(String, Var)] {
        &self.params
    }

    /// Runs the backward pass from `out` with output gradient `seed` (the loss's gradient
    /// with respect to `out`).
    pub fn backward(&self, out: Var, seed: &[f32]) -> Result<Gradients> {
        self.backward_many(&[(out, seed)])
    }

    /// Runs one backward pass from several outputs, each with its loss gradient (a loss
    /// made of several terms: translation, open and rotation).
    pub fn backward_many(&self, seeds: &[(Var, &[f32])]) -> Result<Gradients> {
        let mut grads = Grads {
            grads: (0..self.nodes.len()).map(|_| None).collect(),
            lens: self.nodes.iter().map(|n| n.value.len()).collect(),
            needs: self.nodes.iter().map(|n| n.needs_grad).collect(),
        };
        let mut last = 0;
        for &(out, seed) in seeds {
            let node = self.nodes.get(out.0).ok_or(PolicyError::IndexOutOfRange {
                name: "backward output".into(),
                value: out.0 as i64,
                len: self.nodes.len(),
            })?;
            check_shape("backward seed", seed.len(), &node.shape)?;
            if seed.iter().any(|g| !g.is_finite()) {
                return Err(PolicyError::NonFinite {
                    what: "loss gradient (backward seed)".into(),
                });
            }
            grads.add(out, seed);
            last = last.max(out.0);
        }
        let values = Values(&self.nodes);
        for i in (0..=last).rev() {
            let Some(back) = &self.nodes[i].back else {
                continue;
            };
            // Leaves keep their gradient; an interior node's is consumed here.
            let Some(g) = grads.grads[i].take() else {
                continue;
            };
            match back {
                Backward::Map(f) => f(&values, &g, &mut grads),
                Backward::PassTo(a) => grads.add_owned(*a, g),
            }
        }
        Ok(Gradients { grads: grads.grads })
    }

    /// The gradient of every parameter read, by full key (zeros where none reached it).
    pub fn param_gradients(&self, grads: &Gradients) -> Vec<(String, Vec<f32>)> {
        self.params
            .iter()
            .map(|(k, v)| {
                let g = grads
                    .of(*v)
                    .map_or_else(|| vec![0.0; self.value(*v).len()], <[f32]>::to_vec);
                (k.clone(), g)
            })
            .collect()
    }
}

/// Checks that `len` values fill `shape`.
fn check_shape(what: &str, len: usize, shape: &[usize]) -> Result<()> {
    if shape.iter().product::<usize>() != len {
        return Err(PolicyError::ShapeMismatch {
            name: what.to_string(),
            expected: shape.to_vec(),
            got: vec![len],
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::check::{finite_difference_check, FdOptions};
    use super::*;
    use crate::weights::Weights;

    #[test]
    fn a_reshape_shares_its_values_and_hands_its_gradient_on() {
        let mut t = Tape::new();
        let x = t
            .variable(vec![1.0, -2.0, 3.0, 0.5, 4.0, -1.5], &[2, 3])
            .unwrap();
        let r = t.reshape(x, &[3, 2]).unwrap();
        assert_eq!(t.shape(r), &[3, 2]);
        assert_eq!(t.value(r), t.value(x));
        assert!(
            std::ptr::eq(t.value(r).as_ptr(), t.value(x).as_ptr()),
            "a reshape records no copy"
        );
        // x reaches the outputs three ways: through the sum's two operands (once through
        // the reshape) and through a chain of two reshapes.
        let twice = t.add(r, x).unwrap();
        let chained = t.reshape(r, &[6]).unwrap();
        let seed_twice = [0.5f32, -1.0, 2.0, 0.25, -0.75, 1.5];
        let seed_chained = [1.0f32, 2.0, -3.0, 4.0, -5.0, 6.0];
        let g = t
            .backward_many(&[(twice, &seed_twice), (chained, &seed_chained)])
            .unwrap();
        let expected: Vec<f32> = seed_twice
            .iter()
            .zip(&seed_chained)
            .map(|(a, b)| 2.0 * a + b)
            .collect();
        assert_eq!(g.of(x).unwrap(), expected.as_slice());
    }

    #[test]
    fn a_broadcast_product_is_the_product_with_the_gathered_factors() {
        // x [A=2, B=3, C=2, D=2] times s [2, 2], against `mul` with s gathered to x's
        // shape: values and both gradients bit for bit.
        let dims = [2usize, 3, 2, 2];
        let x: Vec<f32> = (0..24).map(|i| 0.37 * i as f32 - 4.1).collect();
        let s = vec![1.5f32, -0.25, 0.75, 2.0];
        let seed: Vec<f32> = (0..24).map(|i| ((i * 7) % 5) as f32 - 1.7).collect();
        let run = |fused: bool| {
            let mut t = Tape::new();
            let xv = t.variable(x.clone(), &[2, 3, 2, 2]).unwrap();
            let sv = t.variable(s.clone(), &[2, 2]).unwrap();
            let y = if fused {
                t.mul_broadcast(xv, sv, dims).unwrap()
            } else {
                let idx: Vec<usize> = (0..2)
                    .flat_map(|a| {
                        (0..3).flat_map(move |_| (0..2).flat_map(move |c| [a * 2 + c; 2]))
                    })
                    .collect();
                let tiled = t.gather_rows(sv, 1, &idx).unwrap();
                t.mul(xv, tiled).unwrap()
            };
            let g = t.backward(y, &seed).unwrap();
            (
                t.value(y).to_vec(),
                g.of(xv).unwrap().to_vec(),
                g.of(sv).unwrap().to_vec(),
            )
        };
        let (fused, gathered) = (run(true), run(false));
        assert_eq!(fused, gathered);
        // Flat index ((a·B + b)·C + c)·D + d reads s[a·C + c].
        assert_eq!(fused.0[5], x[5] * s[0], "a 0, b 1, c 0");
        assert_eq!(fused.0[7], x[7] * s[1], "a 0, b 1, c 1");
        assert_eq!(fused.0[12], x[12] * s[2], "a 1, b 0, c 0");
        let mut t = Tape::new();
        let xv = t.variable(x.clone(), &[24]).unwrap();
        let sv = t.variable(vec![0.0; 3], &[3]).unwrap();
        assert!(
            t.mul_broadcast(xv, sv, dims).is_err(),
            "factors of the wrong length are an error"
        );
    }

    #[test]
    fn gradients_through_reshapes_match_finite_differences() {
        let w = Weights::from_tensors("none", Default::default());
        let x = (vec![0.3f32, -0.7, 1.1, 0.9], vec![2, 2]);
        let report = finite_difference_check(
            &w,
            "",
            std::slice::from_ref(&x),
            FdOptions::default(),
            |t, _, v| {
                // x ⊙ x through two reshapes of the same input: the first hands its
                // gradient buffer on, the second adds to it.
                let a = t.reshape(v[0], &[4])?;
                let b = t.reshape(v[0], &[4, 1])?;
                let y = t.mul(a, b)?;
                t.reshape(y, &[1, 4])
            },
        )
        .unwrap();
        assert!(report.passed(), "{report:?}");
    }
}
