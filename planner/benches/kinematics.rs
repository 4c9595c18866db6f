//! FK and IK timings (criterion). Reference: analytic UR IK runs in about a microsecond.
#![allow(missing_docs)] // criterion_group! generates an undocumented public fn.

use criterion::{criterion_group, Criterion};
use planner::kinematics::UR5;
use planner::RobotModel;
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let Ok(model) = RobotModel::ur5() else {
        return;
    };
    let q = [0.3, -1.2, 1.1, -0.4, 1.3, -2.0];
    let target = model.fk_tcp(&q);
    let flange = *UR5.forward(&q).isometry();
    c.bench_function("fk_dh_flange", |b| b.iter(|| UR5.forward(black_box(&q))));
    c.bench_function("fk_urdf_tcp", |b| b.iter(|| model.fk_tcp(black_box(&q))));
    c.bench_function("ik_flange_8_solutions", |b| {
        b.iter(|| planner::ik::ik_flange(&UR5, black_box(&flange)))
    });
    c.bench_function("ik_tcp_wrapped", |b| {
        b.iter(|| model.ik(black_box(&target)))
    });
}

criterion_group!(benches, bench);

/// Runs the FK/IK benchmarks.
fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
}
