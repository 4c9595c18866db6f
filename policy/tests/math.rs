//! Behaviour of the plain-Rust math: spherical harmonics, Wigner-D, edge frames, grids,
//! FPS and kNN, on seeded random inputs.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests may unwrap (CONVENTIONS 6)

mod common;
use common::random_rotation;
use nalgebra::{DVector, Matrix3, Vector3};
use policy::grids::{reduced_coefficients, so3_healpix_grid, S2Grid};
use policy::layers::{rotate_embedding, separable_s2_activation};
use policy::points::{
    coefficient_max_pool, coefficient_max_pool_choices, coefficient_max_pool_threads,
    farthest_point_sampling, knn, knn_threads, upsample_weights, UpsampleDistance,
};
use policy::so3::{
    angles_to_matrix, edge_rot_mat, matrix_to_angles, spherical_harmonics, WignerCalculator,
};
use policy::PolicyError;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_vec(rng: &mut ChaCha8Rng) -> [f64; 3] {
    [
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    ]
}

#[test]
fn sh_rotates_with_wigner_d_on_random_inputs() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let lmax = 6;
    let calc = WignerCalculator::new(lmax).unwrap();
    let mut worst = 0.0f64;
    for _ in 0..500 {
        let r = random_rotation(&mut rng);
        let v = random_vec(&mut rng);
        let rv = r * Vector3::from(v);
        let y = DVector::from_vec(spherical_harmonics(lmax, v).unwrap());
        let yr = DVector::from_vec(spherical_harmonics(lmax, [rv[0], rv[1], rv[2]]).unwrap());
        let d = calc.wigner(lmax, &r).unwrap();
        worst = worst.max((d * y - yr).amax());
    }
    assert!(worst < 1e-10, "Y(Rv) - D(R)Y(v) = {worst}");
}

#[test]
fn sh_component_normalisation_and_l1_convention() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    for _ in 0..100 {
        let v = random_vec(&mut rng);
        let y = spherical_harmonics(5, v).unwrap();
        for l in 0..=5 {
            let s: f64 = y[l * l..(l + 1) * (l + 1)].iter().map(|a| a * a).sum();
            assert!((s - (2 * l + 1) as f64).abs() < 1e-10, "l={l}: {s}");
        }
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        for k in 0..3 {
            assert!((y[1 + k] - 3f64.sqrt() * v[k] / n).abs() < 1e-12);
        }
    }
    // The pole is y: Y_l0 at +y is sqrt(2l+1), every m != 0 vanishes.
    let y = spherical_harmonics(4, [0.0, 2.0, 0.0]).unwrap();
    for l in 0..=4usize {
        for m in 0..2 * l + 1 {
            let expect = if m == l {
                ((2 * l + 1) as f64).sqrt()
            } else {
                0.0
            };
            assert!((y[l * l + m] - expect).abs() < 1e-12);
        }
    }
}

/// The edge frames' block-diagonal D in f32 (degrees 0 and 1 written directly, the others
/// from the samples) is the per-degree D rounded to f32, for every calculator degree.
#[test]
fn edge_frame_wigners_are_the_wigner_matrices_in_f32() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for lmax in 0..=4 {
        let calc = WignerCalculator::new(lmax).unwrap();
        let k = (lmax + 1) * (lmax + 1);
        let (mut sh, mut out) = (Vec::new(), vec![f32::NAN; k * k]);
        for _ in 0..200 {
            let r = random_rotation(&mut rng);
            calc.wigner_all_into(&r, &mut sh, &mut out);
            let d = calc.wigner(lmax, &r).unwrap();
            for i in 0..k {
                for j in 0..k {
                    let want = d[(i, j)];
                    let got = f64::from(out[i * k + j]);
                    assert!(
                        (got - want).abs() <= 1e-7 * want.abs().max(1e-3),
                        "lmax {lmax}: D[{i}, {j}] = {got}, want {want}"
                    );
                }
            }
        }
    }
}

#[test]
fn wigner_is_an_orthogonal_representation() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let calc = WignerCalculator::new(4).unwrap();
    for _ in 0..50 {
        let a = random_rotation(&mut rng);
        let b = random_rotation(&mut rng);
        let da = calc.wigner(4, &a).unwrap();
        let db = calc.wigner(4, &b).unwrap();
        let dab = calc.wigner(4, &(a * b)).unwrap();
        assert!((&da * &db - dab).amax() < 1e-10);
        assert!((&da * da.transpose() - nalgebra::DMatrix::identity(25, 25)).amax() < 1e-10);
        // The l = 1 block is the rotation itself.
        assert!((da.view((1, 1), (3, 3)) - a).amax() < 1e-10);
    }
}

#[test]
fn angles_round_trip() {
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    for _ in 0..200 {
        let r = random_rotation(&mut rng);
        let (a, b, g) = matrix_to_angles(&r).unwrap();
        assert!((angles_to_matrix(a, b, g) - r).amax() < 1e-9);
    }
}

#[test]
fn edge_frame_maps_edge_to_y_and_is_a_rotation() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for _ in 0..500 {
        let v = random_vec(&mut rng);
        let m = edge_rot_mat(v).unwrap();
        let u = Vector3::from(v).normalize();
        assert!((m * u - Vector3::y()).amax() < 1e-12);
        assert!((m.transpose() * m - Matrix3::identity()).amax() < 1e-12);
        assert!((m.determinant() - 1.0).abs() < 1e-12);
    }
}

#[test]
fn bad_input_is_a_typed_error() {
    assert!(matches!(
        spherical_harmonics(3, [0.0, 0.0, 0.0]),
        Err(PolicyError::NoDirection { .. })
    ));
    assert!(matches!(
        spherical_harmonics(3, [f64::NAN, 1.0, 0.0]),
        Err(PolicyError::NoDirection { .. })
    ));
    assert!(matches!(
        edge_rot_mat([0.0; 3]),
        Err(PolicyError::NoDirection { .. })
    ));
    let calc = WignerCalculator::new(2).unwrap();
    assert!(matches!(
        calc.wigner(2, &(Matrix3::identity() * 2.0)),
        Err(PolicyError::NotARotation { .. })
    ));
    assert!(matches!(
        calc.wigner(3, &Matrix3::identity()),
        Err(PolicyError::UnsupportedDegree { .. })
    ));
    let pts = vec![[0.0f32, 0.0, 0.0], [1.0, f32::NAN, 0.0]];
    assert!(matches!(
        farthest_point_sampling(&pts, 1),
        Err(PolicyError::NonFinitePoint { index: 1, .. })
    ));
    assert!(matches!(
        farthest_point_sampling(&pts[..1], 2),
        Err(PolicyError::TooFewPoints {
            needed: 2,
            got: 1,
            ..
        })
    ));
    assert!(matches!(
        knn(&[], &pts[..1], 3),
        Err(PolicyError::TooFewPoints { .. })
    ));
    assert!(matches!(
        coefficient_max_pool(&[0.0; 3], 1, 1, 1, &[vec![0]]),
        Err(PolicyError::ShapeMismatch { .. })
    ));
    assert!(matches!(
        coefficient_max_pool(&[0.0; 4], 1, 1, 1, &[vec![1]]),
        Err(PolicyError::IndexOutOfRange { .. })
    ));
}

#[test]
fn max_pool_takes_the_largest_block_by_its_definition_on_any_thread_count() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let (n, lmax, c) = (90, 2, 5);
    let nc = (lmax + 1) * (lmax + 1);
    // Values from a few levels, so that blocks tie; one NaN block.
    let mut x: Vec<f32> = (0..n * nc * c)
        .map(|_| rng.random_range(-2i32..=2) as f32)
        .collect();
    x[(7 * nc + 1) * c + 2] = f32::NAN;
    let mut neighbours: Vec<Vec<usize>> = (0..200)
        .map(|_| {
            (0..rng.random_range(1..8))
                .map(|_| rng.random_range(0..n))
                .collect()
        })
        .collect();
    neighbours[3] = Vec::new();
    neighbours[4] = vec![7, 8];
    // The definition: per centre, degree and channel the first neighbour whose block has
    // the largest sum of squares (a later one only when strictly larger).
    let mut want = vec![0.0f32; neighbours.len() * nc * c];
    for (m, nb) in neighbours.iter().enumerate() {
        for l in 0..=lmax {
            for ch in 0..c {
                let norm = |j: usize| -> f32 {
                    (l * l..(l + 1) * (l + 1))
                        .map(|i| x[(j * nc + i) * c + ch].powi(2))
                        .fold(0.0, |a, b| a + b)
                };
                let mut best: Option<usize> = None;
                for &j in nb {
                    if best.is_none_or(|b| norm(j) > norm(b)) {
                        best = Some(j);
                    }
                }
                if let Some(j) = best {
                    for i in l * l..(l + 1) * (l + 1) {
                        want[(m * nc + i) * c + ch] = x[(j * nc + i) * c + ch];
                    }
                }
            }
        }
    }
    let one = coefficient_max_pool(&x, n, lmax, c, &neighbours).unwrap();
    let same = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(p, q)| p.to_bits() == q.to_bits());
    assert_eq!(one.len(), want.len());
    assert!(same(&one, &want), "the pool is its definition");
    // The NaN block was the first neighbour of centre 4, degree 1, channel 2: kept.
    assert!(one[(4 * nc + 1) * c + 2].is_nan());
    assert!(
        one[3 * nc * c..4 * nc * c].iter().all(|v| *v == 0.0),
        "no neighbours: zero"
    );
    let choices = coefficient_max_pool_choices(&x, n, lmax, c, &neighbours).unwrap();
    assert!(choices[3 * (lmax + 1) * c..4 * (lmax + 1) * c]
        .iter()
        .all(|j| *j == usize::MAX));
    for threads in [2, 3, 8] {
        let pooled = coefficient_max_pool_threads(&x, n, lmax, c, &neighbours, threads).unwrap();
        assert!(same(&pooled, &one), "{threads} threads");
    }
    assert!(matches!(
        coefficient_max_pool_threads(&x, n, lmax, c, &[vec![0], vec![n]], 2),
        Err(PolicyError::IndexOutOfRange { .. })
    ));
}

#[test]
fn fps_picks_are_spread_and_knn_matches_brute_force() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let pts: Vec<[f32; 3]> = (0..300)
        .map(|_| {
            [
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            ]
        })
        .collect();
    let picks = farthest_point_sampling(&pts, 40).unwrap();
    assert_eq!(picks.len(), 40);
    assert!(
        picks.windows(2).all(|w| w[0] < w[1]),
        "sorted, no duplicates"
    );
    assert_eq!(picks[0], 0);
    // Greedy FPS covers the cloud: every point is within the minimum pairwise pick distance.
    let d = |a: &[f32; 3], b: &[f32; 3]| {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    let min_pair = picks
        .iter()
        .flat_map(|&i| picks.iter().filter(move |&&j| j != i).map(move |&j| (i, j)))
        .map(|(i, j)| d(&pts[i], &pts[j]))
        .fold(f32::INFINITY, f32::min);
    let cover = pts
        .iter()
        .map(|p| {
            picks
                .iter()
                .map(|&i| d(p, &pts[i]))
                .fold(f32::INFINITY, f32::min)
        })
        .fold(0.0f32, f32::max);
    assert!(
        cover <= min_pair + 1e-6,
        "cover {cover} vs spacing {min_pair}"
    );

    let queries: Vec<[f32; 3]> = pts.iter().step_by(7).copied().collect();
    let nn = knn(&pts, &queries, 16).unwrap();
    for (q, nb) in queries.iter().zip(&nn) {
        let mut all: Vec<(f32, usize)> =
            pts.iter().enumerate().map(|(i, p)| (d(p, q), i)).collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let expect: Vec<usize> = all.iter().take(16).map(|x| x.1).collect();
        assert_eq!(nb, &expect);
        assert_eq!(
            d(&pts[nb[0]], q),
            0.0,
            "a cloud point is its own nearest neighbour"
        );
    }
}

#[test]
fn knn_breaks_distance_ties_by_index_for_any_count() {
    // A 5 × 5 × 5 grid: every query has many neighbours at exactly equal distances.
    let pts: Vec<[f32; 3]> = (0..125)
        .map(|i| [(i % 5) as f32, ((i / 5) % 5) as f32, (i / 25) as f32])
        .collect();
    let queries = [
        [2.0, 2.0, 2.0],
        [0.0, 0.0, 0.0],
        [0.5, 4.0, 1.5],
        [-3.0, 9.0, 2.0],
    ];
    for k in [0, 1, 6, 7, 33, 124, 125, 200] {
        let nn = knn_threads(&pts, &queries, k, 2).unwrap();
        for (q, nb) in queries.iter().zip(&nn) {
            let d2 = |p: &[f32; 3]| (0..3).map(|a| (p[a] - q[a]) * (p[a] - q[a])).sum::<f32>();
            let mut all: Vec<(f32, usize)> =
                pts.iter().enumerate().map(|(i, p)| (d2(p), i)).collect();
            all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            let expect: Vec<usize> = all.iter().take(k).map(|x| x.1).collect();
            assert_eq!(nb, &expect, "k = {k}, query {q:?}");
        }
    }
}

#[test]
fn euclidean_upsampling_weights_are_rotation_invariant_and_l1_are_not() {
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let pts: Vec<[f32; 3]> = (0..64)
        .map(|_| {
            [
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            ]
        })
        .collect();
    let centres: Vec<[f32; 3]> = pts.iter().step_by(4).copied().collect();
    let nb = knn(&centres, &pts, 3).unwrap();
    let r = random_rotation(&mut rng);
    let rot = |p: &[f32; 3]| {
        let v = r * Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
        [v[0] as f32, v[1] as f32, v[2] as f32]
    };
    let rp: Vec<_> = pts.iter().map(rot).collect();
    let rc: Vec<_> = centres.iter().map(rot).collect();
    let max_diff = |d| {
        let a = upsample_weights(&pts, &centres, &nb, d).unwrap();
        let b = upsample_weights(&rp, &rc, &nb, d).unwrap();
        a.iter()
            .flatten()
            .zip(b.iter().flatten())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max)
    };
    assert!(max_diff(UpsampleDistance::Euclidean) < 1e-4);
    assert!(max_diff(UpsampleDistance::L1) > 1e-3);
}

#[test]
fn s2_activation_becomes_equivariant_on_finer_grids() {
    // The reference grid for (3, 3) is coarse; a finer grid reduces the equivariance error.
    let mut rng = ChaCha8Rng::seed_from_u64(14);
    let lmax = 3;
    let calc = WignerCalculator::new(lmax).unwrap();
    let n = 16;
    let x: Vec<f32> = (0..n * 16).map(|_| rng.random_range(-0.5..0.5)).collect();
    let r = random_rotation(&mut rng);
    let d = calc.wigner(lmax, &r).unwrap();
    let rotate = |v: &[f32]| -> Vec<f32> {
        (0..n)
            .flat_map(|z| {
                let col = DVector::from_iterator(
                    16,
                    v[z * 16..(z + 1) * 16].iter().map(|a| f64::from(*a)),
                );
                (&d * col).iter().map(|a| *a as f32).collect::<Vec<_>>()
            })
            .collect()
    };
    let err = |g: &S2Grid| {
        let a = rotate(&g.activate(&x, n, 1).unwrap());
        let b = g.activate(&rotate(&x), n, 1).unwrap();
        a.iter()
            .zip(&b)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0f32, f32::max)
    };
    let coarse = err(&S2Grid::reference(3, 3).unwrap());
    let fine = err(&S2Grid::with_resolution(3, 3, 40, 41).unwrap());
    assert!(fine < coarse / 10.0, "coarse {coarse} fine {fine}");
    assert_eq!(reduced_coefficients(3, 2).len(), 14);
}

#[test]
fn gated_activation_commutes_with_rotations() {
    // Every l > 0 block is multiplied by an invariant scalar, so D(R) commutes with it up to
    // f32 rounding, both gated by the layer's own scalars and by each channel's l = 0 value.
    let mut rng = ChaCha8Rng::seed_from_u64(15);
    let lmax = 3;
    let calc = WignerCalculator::new(lmax).unwrap();
    let (n, c) = (16, 5);
    let k = 16;
    let x: Vec<f32> = (0..n * k * c)
        .map(|_| rng.random_range(-2.0..2.0))
        .collect();
    let gating: Vec<f32> = (0..n * c).map(|_| rng.random_range(-3.0..3.0)).collect();
    let g = S2Grid::gate(lmax, lmax).unwrap();
    assert_eq!(g.num_points(), 0);
    for _ in 0..5 {
        let r = random_rotation(&mut rng);
        let d = calc.wigner(lmax, &r).unwrap();
        let rotate = |v: &[f32]| rotate_embedding(v, c, &d).unwrap();
        let rel = |a: &[f32], b: &[f32]| {
            let m = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            a.iter()
                .zip(b)
                .map(|(p, q)| (p - q).abs())
                .fold(0.0f32, f32::max)
                / m
        };
        let own = rel(
            &rotate(&g.activate(&x, n, c).unwrap()),
            &g.activate(&rotate(&x), n, c).unwrap(),
        );
        let sep = rel(
            &rotate(&separable_s2_activation(&g, &gating, &x, c).unwrap()),
            &separable_s2_activation(&g, &gating, &rotate(&x), c).unwrap(),
        );
        assert!(own < 2e-6 && sep < 2e-6, "own gate {own}, layer gate {sep}");
    }
    // The l = 0 row is SiLU of the gate, the others are scaled by its sigmoid.
    let y = separable_s2_activation(&g, &gating, &x, c).unwrap();
    let s = 1.0 / (1.0 + (-gating[2]).exp());
    assert!((y[2] - gating[2] * s).abs() < 1e-6);
    assert!((y[c + 2] - x[c + 2] * s).abs() < 1e-6);
}

#[test]
fn healpix_grid_sizes_and_rotations() {
    for (level, n) in [(0u32, 72usize), (1, 576), (2, 4608)] {
        let g = so3_healpix_grid(level);
        assert_eq!(g.len(), n);
        for r in g.iter().step_by(37) {
            assert!((r.matrix.transpose() * r.matrix - Matrix3::identity()).amax() < 1e-12);
        }
    }
}
