//! Times the parts of the cloud build on the first valid problem of every MBM scene
//! (`cargo run --release -p planner --example cloud_build`).
#![allow(clippy::unwrap_used, missing_docs)]
use cpu_time::ThreadTime as Instant;
use planner::kdtree::KdTree;
use planner::mbm::{MbmFile, MBM_PROBLEMS_PATH};
use planner::world::{CloudParams, DistanceField};

fn main() {
    let file = MbmFile::parse(&std::fs::read_to_string(MBM_PROBLEMS_PATH).unwrap()).unwrap();
    for (scene, ps) in &file.problems {
        let p = ps.iter().find(|p| p.valid).unwrap();
        let mut best = [f64::INFINITY; 3];
        let mut dims = [0; 3];
        let mut n = 0;
        for _ in 0..5 {
            let t = Instant::now();
            let c = p.surface_cloud(0.01).unwrap();
            let a = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let f = DistanceField::build(&c.points, &CloudParams::default())
                .unwrap()
                .unwrap();
            let b = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let k = KdTree::build(&c.points);
            let d = t.elapsed().as_secs_f64();
            std::hint::black_box(k);
            dims = f.dims();
            n = c.len();
            for (x, y) in best.iter_mut().zip([a, b, d]) {
                *x = x.min(y * 1e3);
            }
        }
        println!(
            "{scene:18} {n:7} pts dims {dims:?} ({:.1} M cells): sample {:.2} ms, field(+tree) {:.2} ms, tree {:.2} ms",
            (dims[0] * dims[1] * dims[2]) as f64 / 1e6,
            best[0],
            best[1],
            best[2]
        );
    }
}
