//! IK of one MBM goal pose against the goal (`cargo run -p planner --example ik_check -- table_pick 34`).
#![allow(clippy::unwrap_used, missing_docs)]
use planner::mbm::{mbm_robot_with_ik, MbmFile, MBM_PROBLEMS_PATH};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let file = MbmFile::parse(&std::fs::read_to_string(MBM_PROBLEMS_PATH).unwrap()).unwrap();
    let idx: usize = a[2].parse().unwrap();
    let p = file.problems[&a[1]]
        .iter()
        .find(|p| p.index == idx)
        .unwrap();
    let m = mbm_robot_with_ik().unwrap();
    let (s, g) = p.start_goal().unwrap();
    println!("goal {g:?}\nlimits {:?}", m.limits);
    let pose = m.fk_tcp(&g);
    for q in m.ik_near(&pose, &s).unwrap() {
        println!("sol {q:?}");
    }
    let ik = m.ik_data().unwrap();
    let flange = ik.root_from_dh.inverse() * pose.isometry() * ik.flange_from_tcp.inverse();
    for q in planner::ik::ik_flange(&ik.ur, &flange).unwrap() {
        println!("raw {q:?}");
    }
}
