//! Equivariance of each layer: rotating the input features by D(R) (and the geometry by R)
//! rotates the output by D(R). Layers use the fixtures' weights on seeded random inputs.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests may unwrap (CONVENTIONS 6)

mod common;
use common::random_rotation;
use std::path::{Path, PathBuf};

use nalgebra::{DMatrix, Matrix3, Vector3};
use policy::layers::{rotate_embedding, FilmLinear, RmsNormSh, So3Linear};
use policy::so3::WignerCalculator;
use policy::weights::Weights;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(format!("{name}.safetensors"))
}

fn random_values(rng: &mut ChaCha8Rng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(-1.5f32..1.5)).collect()
}

fn wigner(r: &Matrix3<f64>, lmax: usize) -> DMatrix<f64> {
    WignerCalculator::new(lmax)
        .unwrap()
        .wigner(lmax, r)
        .unwrap()
}

/// max |a - b| / max |b|.
fn rel_err(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    let m = b.iter().fold(0.0f64, |m, v| m.max(f64::from(v.abs())));
    let d = a
        .iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max(f64::from((x - y).abs())));
    d / m
}

/// Checks f(D x) = D f(x) for a per-node map f on `[n, 16, cin]` features.
fn check_layer(name: &str, cin: usize, cout: usize, f: impl Fn(&[f32]) -> Vec<f32>) {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for _ in 0..5 {
        let r = random_rotation(&mut rng);
        let d = wigner(&r, 3);
        let x = random_values(&mut rng, 10 * 16 * cin);
        let y = f(&x);
        let y_of_rot = f(&rotate_embedding(&x, cin, &d).unwrap());
        let rot_of_y = rotate_embedding(&y, cout, &d).unwrap();
        let e = rel_err(&y_of_rot, &rot_of_y);
        assert!(e < 1e-5, "{name}: relative equivariance error {e}");
    }
}

#[test]
fn so3_linear_rms_norm_and_film_are_equivariant() {
    let w = Weights::from_file(&fixture("linear_norm_rbf")).unwrap();
    let p = w.scope("param.");
    let lin = So3Linear::load(&p.sub("so3_linear")).unwrap();
    check_layer("so3_linear", 16, 24, |x| lin.forward(x).unwrap());
    let norm = RmsNormSh::load_any(&p.sub("rms_norm")).unwrap();
    check_layer("rms_norm", 16, 16, |x| norm.forward(x).unwrap());
    let film = FilmLinear::load(&p.sub("film_linear"), 3, 8, 12).unwrap();
    let cond: Vec<f32> = (0..256).map(|i| ((i as f32) * 0.37).sin()).collect();
    check_layer("film_linear", 8, 12, |x| film.forward(x, &cond).unwrap());
}

#[test]
fn per_degree_scalar_film_is_equivariant() {
    // The paper's iFiLM on random weights of its own layout (lmax 3, 8 -> 8 channels).
    use policy::init::{random_weights, ExtraSizes};
    use policy::layers::ScalarFilmLinear;
    use policy::model::ModelConfig;
    use policy::transblock::FilmKind;
    let mut cfg = ModelConfig::reference();
    cfg.sphere_channels = vec![8; 5];
    cfg.attn_hidden_channels = vec![8; 4];
    cfg.ffn_hidden_channels = vec![8; 4];
    cfg.field_nn_c = 8;
    cfg.film_kind = FilmKind::PerDegreeScalar;
    let mut extra = ExtraSizes::reference();
    extra.film_dim = 16;
    extra.token_dim = 8;
    extra.lang_depth = 1;
    extra.num_distance_basis = 8;
    extra.field_num_basis = 8;
    let w = random_weights(&cfg, &extra, 3);
    let film = ScalarFilmLinear::load(&w.scope("down_blocks.0.block.transblock.ffn.so3_linear_1."))
        .unwrap();
    let cond: Vec<f32> = (0..16).map(|i| ((i as f32) * 0.37).sin()).collect();
    check_layer("scalar film", 8, 8, |x| film.forward(x, &cond).unwrap());
}

#[test]
fn weights_report_missing_and_misshapen_parameters_by_name() {
    let w = Weights::from_file(&fixture("linear_norm_rbf")).unwrap();
    let p = w.scope("param.");
    let e = p.sub("so3_linear").f32("weight", &[4, 24, 15]).unwrap_err();
    let msg = e.to_string();
    assert!(msg.contains("param.so3_linear.weight"), "{msg}");
    assert!(msg.contains("[4, 24, 16]"), "{msg}");
    let e = So3Linear::load(&p.sub("nonexistent")).unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("param.nonexistent.weight") && msg.contains("missing"),
        "{msg}"
    );
}

#[test]
fn so2_convolution_in_edge_frames_is_equivariant() {
    use policy::so2_conv::{CoefficientMapping, EdgeWigners, So2Conv};
    let w = Weights::from_file(&fixture("so2_conv")).unwrap();
    let p = w.scope("param.");
    let map = CoefficientMapping::new(3, 2).unwrap();
    let conv = So2Conv::load(&p.sub("so2_conv_1"), &map, 16, 16, 24, true).unwrap();
    let calc = WignerCalculator::new(3).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let edges = 20;
    let run = |x: &[f32], ev: &[[f32; 3]], x_edge: &[f32]| {
        let wig = EdgeWigners::new(&calc, 3, ev).unwrap();
        let (y, extra) = conv
            .forward(&wig.rotate(&map, x, 16).unwrap(), Some(x_edge))
            .unwrap();
        (wig.rotate_back(&map, &y, 16).unwrap(), extra)
    };
    for _ in 0..3 {
        let r = random_rotation(&mut rng);
        let d = wigner(&r, 3);
        let x = random_values(&mut rng, edges * 16 * 16);
        let x_edge = random_values(&mut rng, edges * 16);
        let ev: Vec<[f32; 3]> = (0..edges)
            .map(|_| {
                [
                    rng.random_range(-1.0f32..1.0),
                    rng.random_range(-1.0f32..1.0),
                    rng.random_range(-1.0f32..1.0),
                ]
            })
            .collect();
        let ev_rot: Vec<[f32; 3]> = ev
            .iter()
            .map(|v| {
                let u = r * Vector3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]));
                [u[0] as f32, u[1] as f32, u[2] as f32]
            })
            .collect();
        let (y, extra) = run(&x, &ev, &x_edge);
        let (y_rot, extra_rot) = run(&rotate_embedding(&x, 16, &d).unwrap(), &ev_rot, &x_edge);
        let e = rel_err(&y_rot, &rotate_embedding(&y, 16, &d).unwrap());
        assert!(e < 1e-5, "SO(2) conv: relative equivariance error {e}");
        let e = rel_err(&extra_rot, &extra);
        assert!(
            e < 1e-5,
            "SO(2) conv extra scalars: relative invariance error {e}"
        );
    }
}

/// A small random cloud with its 6-NN graph (self edge dropped), edges grouped by destination.
fn knn_graph(rng: &mut ChaCha8Rng, n: usize) -> (Vec<[f32; 3]>, Vec<usize>, Vec<usize>) {
    let pos: Vec<[f32; 3]> = (0..n)
        .map(|_| {
            [
                rng.random_range(-0.2f32..0.2),
                rng.random_range(-0.2f32..0.2),
                rng.random_range(-0.2f32..0.2),
            ]
        })
        .collect();
    let nb = policy::points::knn(&pos, &pos, 7).unwrap();
    let (mut src, mut dst) = (Vec::new(), Vec::new());
    for (d, row) in nb.iter().enumerate() {
        for &s in row.iter().filter(|&&s| s != d) {
            src.push(s);
            dst.push(d);
        }
    }
    (pos, src, dst)
}

fn rotate_points(r: &Matrix3<f64>, pos: &[[f32; 3]]) -> Vec<[f32; 3]> {
    pos.iter()
        .map(|v| {
            let u = r * Vector3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]));
            [u[0] as f32, u[1] as f32, u[2] as f32]
        })
        .collect()
}

/// Relative equivariance error of the fixture's graph attention with an S2 grid of
/// `lat` × `long` points, over 3 random rotations.
fn attention_equivariance_error(lat: usize, long: usize) -> f64 {
    use policy::attention::{AttentionConfig, EdgeSet, GraphAttention};
    use policy::grids::S2Grid;
    use policy::layers::GaussianRbf;
    let w = Weights::from_file(&fixture("graph_attention")).unwrap();
    let p = w.scope("param.");
    let cfg = AttentionConfig {
        lmax: 3,
        mmax: 2,
        sphere_channels: 16,
        hidden_channels: 16,
        num_heads: 2,
        alpha_channels: 8,
        value_channels: 8,
        output_channels: 16,
    };
    let grid = S2Grid::with_resolution(3, 2, lat, long).unwrap();
    let ga = GraphAttention::load_with_grid(&p, cfg, grid).unwrap();
    let rbf = GaussianRbf::load(&p.sub("distance_expansion"), 0.396).unwrap();
    let calc = WignerCalculator::new(3).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let mut worst = 0.0f64;
    for _ in 0..3 {
        let (pos, src, dst) = knn_graph(&mut rng, 24);
        let r = random_rotation(&mut rng);
        let d = wigner(&r, 3);
        let x = random_values(&mut rng, 24 * 16 * 16);
        let e = EdgeSet::new(&calc, 3, &pos, &pos, src.clone(), dst.clone(), &rbf).unwrap();
        let y = ga.forward(&x, &x, &e).unwrap();
        let pos_r = rotate_points(&r, &pos);
        let e_r = EdgeSet::new(&calc, 3, &pos_r, &pos_r, src, dst, &rbf).unwrap();
        let x_r = rotate_embedding(&x, 16, &d).unwrap();
        let y_r = ga.forward(&x_r, &x_r, &e_r).unwrap();
        worst = worst.max(rel_err(&y_r, &rotate_embedding(&y, 16, &d).unwrap()));
    }
    worst
}

#[test]
fn graph_attention_is_equivariant_with_a_fine_s2_grid() {
    // The reference's 8 x 5 grid is far from equivariant; a fine grid is close.
    let coarse = attention_equivariance_error(8, 5);
    let fine = attention_equivariance_error(48, 48);
    println!("graph attention equivariance: reference grid {coarse:.2e}, 48x48 grid {fine:.2e}");
    assert!(
        coarse > 1e-2,
        "reference grid unexpectedly equivariant: {coarse}"
    );
    assert!(fine < 1e-3, "fine grid: relative equivariance error {fine}");
}

/// Relative equivariance error of the fixture's TransBlock (FiLM on) with the given grids.
fn transblock_equivariance_error(fine: bool) -> f64 {
    use policy::attention::{AttentionConfig, EdgeSet};
    use policy::grids::S2Grid;
    use policy::layers::GaussianRbf;
    use policy::transblock::{TransBlock, TransBlockConfig};
    let w = Weights::from_file(&fixture("transblock")).unwrap();
    let p = w.scope("param.");
    let cfg = TransBlockConfig {
        attn: AttentionConfig {
            lmax: 3,
            mmax: 2,
            sphere_channels: 16,
            hidden_channels: 16,
            num_heads: 2,
            alpha_channels: 8,
            value_channels: 8,
            output_channels: 16,
        },
        ffn_hidden_channels: 16,
        output_channels: 24,
        film: Some(policy::transblock::FilmKind::Hypernetwork),
    };
    let block = if fine {
        TransBlock::load_with_grids(
            &p,
            cfg,
            S2Grid::with_resolution(3, 2, 48, 48).unwrap(),
            S2Grid::with_resolution(3, 3, 48, 48).unwrap(),
        )
        .unwrap()
    } else {
        TransBlock::load(&p, cfg).unwrap()
    };
    let rbf = GaussianRbf::load(&p.sub("distance_expansion"), 0.396).unwrap();
    let calc = WignerCalculator::new(3).unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(14);
    let cond = random_values(&mut rng, 128);
    let mut worst = 0.0f64;
    for _ in 0..2 {
        let (pos, src, dst) = knn_graph(&mut rng, 24);
        let r = random_rotation(&mut rng);
        let d = wigner(&r, 3);
        let x = random_values(&mut rng, 24 * 16 * 16);
        let e = EdgeSet::new(&calc, 3, &pos, &pos, src.clone(), dst.clone(), &rbf).unwrap();
        let y = block.forward(&x, &x, &e, Some(&cond)).unwrap();
        let pos_r = rotate_points(&r, &pos);
        let e_r = EdgeSet::new(&calc, 3, &pos_r, &pos_r, src, dst, &rbf).unwrap();
        let x_r = rotate_embedding(&x, 16, &d).unwrap();
        let y_r = block.forward(&x_r, &x_r, &e_r, Some(&cond)).unwrap();
        worst = worst.max(rel_err(&y_r, &rotate_embedding(&y, 24, &d).unwrap()));
    }
    worst
}

#[test]
fn transblock_is_equivariant_with_fine_s2_grids() {
    let coarse = transblock_equivariance_error(false);
    let fine = transblock_equivariance_error(true);
    println!("transblock equivariance: reference grids {coarse:.2e}, 48x48 grids {fine:.2e}");
    assert!(
        coarse > 1e-2,
        "reference grids unexpectedly equivariant: {coarse}"
    );
    assert!(
        fine < 1e-3,
        "fine grids: relative equivariance error {fine}"
    );
}

/// Worst relative errors (translation logits, open logit, rotation logits on the moved grid)
/// of the fixture's field heads under a random rigid motion.
fn heads_equivariance_errors(res: policy::grids::S2Resolution) -> [f64; 3] {
    use policy::grids::GridRotation;
    use policy::heads::{FieldHeads, FieldHeadsConfig};
    let path = fixture("query_heads");
    let w = Weights::from_file(&path).unwrap();
    let cfg = FieldHeadsConfig {
        field_channels: 8,
        attn_hidden_channels: 8,
        num_heads: 2,
        alpha_channels: 4,
        value_channels: 4,
        ffn_hidden_channels: 16,
        node_lmax: 3,
    };
    let heads = FieldHeads::load_with(&w.scope("param."), cfg, 1, res).unwrap();
    let fx = policy::fixtures::FixtureFile::load(&path).unwrap();
    let emb = fx.f32_any("in.node_embedding").unwrap().1.to_vec();
    let to3 =
        |v: &[f32]| -> Vec<[f32; 3]> { v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect() };
    let pos = to3(fx.f32_any("in.node_coord").unwrap().1);
    let tq = to3(fx.f32_any("in.trans_queries").unwrap().1);
    let rq = to3(fx.f32_any("in.rot_query").unwrap().1)[0];
    let mut rng = ChaCha8Rng::seed_from_u64(15);
    let r = random_rotation(&mut rng);
    let t = [0.1f32, -0.2, 0.05];
    let moved = |p: &[[f32; 3]]| -> Vec<[f32; 3]> {
        rotate_points(&r, p)
            .into_iter()
            .map(|v| [v[0] + t[0], v[1] + t[1], v[2] + t[2]])
            .collect()
    };
    let emb_r = rotate_embedding(&emb, 8, &wigner(&r, 3)).unwrap();
    let tl = heads.trans_logits(&emb, &pos, &tq).unwrap();
    let tl_r = heads
        .trans_logits(&emb_r, &moved(&pos), &moved(&tq))
        .unwrap();
    let q = heads.rot_query(&emb, &pos, rq).unwrap();
    let q_r = heads
        .rot_query(&emb_r, &moved(&pos), moved(&[rq])[0])
        .unwrap();
    let rotated: Vec<GridRotation> = heads
        .grid()
        .iter()
        .map(|g| GridRotation {
            angles: g.angles,
            matrix: r * g.matrix,
        })
        .collect();
    let rl_r = heads.logits_on(&q_r.so3_coeffs, &rotated).unwrap();
    let f = |v: &[f64]| v.iter().map(|x| *x as f32).collect::<Vec<_>>();
    [
        rel_err(&tl_r, &tl),
        f64::from((q_r.open_logit - q.open_logit).abs() / q.open_logit.abs()),
        rel_err(&f(&rl_r), &f(&q.rot_logits)),
    ]
}

#[test]
fn field_heads_are_invariant_and_rotation_logits_move_with_the_scene() {
    use policy::grids::S2Resolution;
    let coarse = heads_equivariance_errors(S2Resolution::Reference);
    let fine = heads_equivariance_errors(S2Resolution::Square(24));
    println!(
        "field heads equivariance (trans, open, rot): reference grids {coarse:?}, 24x24 {fine:?}"
    );
    assert!(
        coarse[2] > 1e-2,
        "reference grids unexpectedly equivariant: {coarse:?}"
    );
    for e in fine {
        assert!(
            e < 1e-4,
            "fine grids: relative equivariance errors {fine:?}"
        );
    }
}
