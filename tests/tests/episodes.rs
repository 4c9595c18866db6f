//! HIL regression: whole episodes in the simulated cell, and the same episodes with faults
//! injected. Each ends in its documented outcome, the arm is left still, and the recording
//! is complete and accepted by the Python `mcap` reader and Foxglove's schemas.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use cell_types::config::CellConfig;
use cell_types::{CameraFrame, Keyframe, TickClock, Transform};
use equact::episode::{run_sim_episode, EpisodeReport, KeyframeSource, Outcome, ScriptedExpert};
use equact::learned::{for_cell, LearnedPolicy};
use equact::recording::EpisodeRecorder;
use equact::sim_cell::SimCell;
use equact::task::{Fruit, TaskInstance, TaskKind};
use firmware_iface::camera::{CameraError, DepthCamera};
use hil_sim::ur_controller::Fault;
use policy::predict::{InstructionEmbedding, Policy, PolicyConfig};

/// Episodes run in real time against loopback servers: one at a time, so two episodes
/// never compete for the two cores of CI.
static SERIAL: Mutex<()> = Mutex::new(());

struct Run {
    report: EpisodeReport,
    still: bool,
    /// The arm's joints at the end.
    final_q: [f64; 6],
}

fn run_episode(
    name: &str,
    seed: u64,
    keyframes: Option<Vec<Keyframe>>,
    setup: impl FnOnce(&mut SimCell),
) -> Run {
    run_episode_with(
        name,
        seed,
        |task| {
            Box::new(ScriptedExpert::new(
                keyframes.unwrap_or_else(|| task.expert_keyframes()),
            ))
        },
        setup,
    )
}

fn run_episode_with(
    name: &str,
    seed: u64,
    source: impl FnOnce(&TaskInstance) -> Box<dyn KeyframeSource>,
    setup: impl FnOnce(&mut SimCell),
) -> Run {
    run_task_episode(
        TaskKind::PickFruit(Fruit::Strawberry),
        name,
        seed,
        source,
        setup,
    )
}

/// An episode of `kind`'s scene with `seed`, driven by `source`.
fn run_task_episode(
    kind: TaskKind,
    name: &str,
    seed: u64,
    source: impl FnOnce(&TaskInstance) -> Box<dyn KeyframeSource>,
    setup: impl FnOnce(&mut SimCell),
) -> Run {
    let _guard = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let cfg = CellConfig::simulated().unwrap();
    // Real time: the faults below are injected after wall-clock delays.
    let clock = Arc::new(TickClock::new(1.0).unwrap());
    let task = TaskInstance::sample(kind, seed, cfg.workspace.table_height);
    let mut cell = SimCell::start(&cfg, task.clone(), seed, clock.clone()).unwrap();
    setup(&mut cell);
    let dir = std::env::temp_dir().join(format!("equact-episodes-{}", std::process::id()));
    let path = dir.join(format!("{name}.mcap"));
    let mut recorder = EpisodeRecorder::create(&path, &BTreeMap::new()).unwrap();
    let mut policy = source(&task);
    let interrupt = Arc::new(AtomicBool::new(false));
    let report = run_sim_episode(
        &cfg,
        &mut cell,
        policy.as_mut(),
        &mut recorder,
        &interrupt,
        clock.as_ref(),
        seed,
    );
    // The arm is left still: the controller's measured joint speeds settle to zero.
    std::thread::sleep(Duration::from_millis(600));
    let snap = cell.controller.snapshot();
    let still = snap.actual_qd.iter().all(|v| v.abs() < 1e-3);
    cell.controller.shutdown();
    Run {
        report,
        still,
        final_q: snap.actual_q,
    }
}

fn check_recording(report: &EpisodeReport) {
    let v = tests::check_recording_with_peer(&report.recording).unwrap();
    assert_eq!(v["outcome"]["outcome"], report.outcome.label());
    for (topic, n) in &report.counts {
        assert_eq!(v["counts"][topic].as_u64(), Some(*n), "{topic}: {v}");
    }
    // Joint states and the TCP come at the controller rate (CB3: 8 ms), not once per step.
    for topic in ["/joint_states", "/tf"] {
        let period = v["median_period_s"][topic].as_f64().unwrap();
        assert!(
            (period - 0.008).abs() < 0.002,
            "{topic}: median period {period} s"
        );
    }
}

#[test]
fn expert_picks_the_fruit_and_the_recording_checks_out() {
    let run = run_episode("success", 0, None, |_| {});
    assert_eq!(
        run.report.outcome,
        Outcome::Success,
        "{}",
        run.report.detail
    );
    assert_eq!(run.report.steps, 3);
    // Above the fruit, closed around it, lifted: one grasp, at the second keyframe, near
    // the fruit's centre (the expert aims at it).
    let events = &run.report.gripper_events;
    assert_eq!(events.len(), 1, "{events:?}");
    assert_eq!(events[0].0, 1, "{events:?}");
    assert!(
        events[0]
            .1
            .to_string()
            .starts_with("grasped the strawberry, its grasp site "),
        "{events:?}"
    );
    assert!(run.still);
    check_recording(&run.report);
    check_plots(&run.report);
}

/// `equact plot` draws one motion picture per keyframe and one scene per step, and the
/// measured joints track the plan within the configured bound.
fn check_plots(report: &EpisodeReport) {
    let out = report.recording.with_extension("plots");
    let written = equact::plot::plot_file(&report.recording, &out).unwrap();
    let names: Vec<String> = written
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    for step in 0..report.steps {
        assert!(
            names.contains(&format!("motion_{step:02}.png")),
            "{names:?}"
        );
        assert!(names.contains(&format!("scene_{step:02}.png")), "{names:?}");
    }
    for path in &written {
        let decoder =
            png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
        let reader = decoder.read_info().unwrap();
        assert!(reader.info().width >= 1000, "{}", path.display());
    }
    let bytes = std::fs::read(&report.recording).unwrap();
    let data = equact::plot::EpisodeData::from_bytes(&bytes).unwrap();
    assert_eq!(data.motions.len(), report.steps);
    for m in &data.motions {
        let e = equact::plot::tracking_error(m, &data.joints);
        assert!(
            e.len() * 2 >= m.samples.len(),
            "step {}: {} errors",
            m.step,
            e.len()
        );
        let worst = e.iter().map(|x| x.1).fold(0.0, f64::max);
        assert!(worst < m.tracking_bound, "step {}: {worst} rad", m.step);
    }
}

#[test]
fn protective_stop_mid_trajectory_ends_in_arm_stopped() {
    let run = run_episode("protective_stop", 1, None, |cell| {
        let injector = cell.controller.injector();
        std::thread::spawn(move || {
            // The first motion takes about two seconds; stop the arm in the middle of it.
            std::thread::sleep(Duration::from_millis(1500));
            injector.inject(Fault::ProtectiveStop);
        });
    });
    assert_eq!(
        run.report.outcome,
        Outcome::ArmStopped,
        "{}",
        run.report.detail
    );
    assert!(
        run.report.detail.contains("ProtectiveStop"),
        "{}",
        run.report.detail
    );
    assert!(run.still);
    check_recording(&run.report);
}

#[test]
fn rtde_connection_drop_ends_in_arm_stopped() {
    let run = run_episode("connection_drop", 2, None, |cell| {
        let injector = cell.controller.injector();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(1500));
            injector.inject(Fault::DropConnections);
        });
    });
    assert_eq!(
        run.report.outcome,
        Outcome::ArmStopped,
        "{}",
        run.report.detail
    );
    assert!(run.still);
    check_recording(&run.report);
}

#[test]
fn gripper_fault_ends_in_gripper_fault() {
    let run = run_episode("gripper_fault", 3, None, |cell| {
        // A major fault (0x0B) after activation, while the arm approaches the fruit: the
        // grasp that follows must report it.
        let gripper = cell.world.gripper_sim().clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(2500));
            gripper.inject_fault(0x0B);
        });
    });
    assert_eq!(
        run.report.outcome,
        Outcome::GripperFault,
        "{}",
        run.report.detail
    );
    assert!(run.still);
    check_recording(&run.report);
}

struct DeadCamera(u8);

impl DepthCamera for DeadCamera {
    fn id(&self) -> u8 {
        self.0
    }
    fn capture(&mut self) -> Result<CameraFrame, CameraError> {
        Err(CameraError::Device {
            camera: self.0,
            message: "no frame within 1 s (USB link lost)".into(),
        })
    }
}

#[test]
fn camera_without_frames_ends_in_perception_fault() {
    let run = run_episode("dead_camera", 4, None, |cell| {
        let id = cell.cameras[1].id();
        cell.cameras[1] = Box::new(DeadCamera(id));
    });
    assert_eq!(
        run.report.outcome,
        Outcome::PerceptionFault,
        "{}",
        run.report.detail
    );
    assert!(run.report.detail.contains("USB link lost"));
    assert_eq!(run.report.steps, 0);
    assert!(run.still);
    check_recording(&run.report);
}

#[test]
fn unreachable_keyframe_ends_in_plan_failed_without_moving() {
    let far = Keyframe {
        base_from_tcp: Transform::from_xyz_rpy([2.5, 0.0, 0.3], [std::f64::consts::PI, 0.0, 0.0]),
        gripper_open: true,
        ignore_collisions: false,
    };
    let run = run_episode("unreachable", 5, Some(vec![far]), |_| {});
    assert_eq!(
        run.report.outcome,
        Outcome::PlanFailed,
        "{}",
        run.report.detail
    );
    assert!(
        run.report.detail.contains("keyframe 0"),
        "{}",
        run.report.detail
    );
    assert!(run.still);
    check_recording(&run.report);
}

/// One keyframe with ranked alternatives (a policy's next-best answers), then done.
struct Ranked {
    ranked: Vec<Keyframe>,
    next: usize,
}

impl KeyframeSource for Ranked {
    fn next_keyframe(
        &mut self,
        _obs: &equact::episode::Observation<'_>,
    ) -> anyhow::Result<Option<Keyframe>> {
        if self.next > 0 {
            return Ok(None);
        }
        self.next = 1;
        Ok(self.ranked.first().copied())
    }

    fn alternative(&mut self) -> anyhow::Result<Option<Keyframe>> {
        let k = self.ranked.get(self.next).copied();
        self.next += 1;
        Ok(k)
    }

    fn name(&self) -> &str {
        "ranked"
    }
}

#[test]
fn a_refused_keyframe_is_replaced_by_the_next_ranked_one() {
    let far = |x: f64| Keyframe {
        base_from_tcp: Transform::from_xyz_rpy([x, 0.0, 0.3], [std::f64::consts::PI, 0.0, 0.0]),
        gripper_open: true,
        ignore_collisions: false,
    };
    // The first two are out of reach; the third, the expert's first keyframe, is executed.
    let target = Arc::new(Mutex::new(None));
    let t = target.clone();
    let run = run_episode_with(
        "ranked",
        6,
        move |task| {
            let reachable = task.expert_keyframes()[0];
            *t.lock().unwrap() = Some(reachable);
            Box::new(Ranked {
                ranked: vec![far(2.5), far(3.0), reachable],
                next: 0,
            })
        },
        |_| {},
    );
    assert_eq!(
        run.report.outcome,
        Outcome::TaskNotDone,
        "{}",
        run.report.detail
    );
    assert_eq!(run.report.steps, 1, "{}", run.report.detail);
    assert_eq!(run.report.counts.get("/keyframes").copied(), Some(3));
    // The arm went to the third-ranked keyframe.
    let reached = planner::model::RobotModel::ur5()
        .unwrap()
        .fk_tcp(&run.final_q)
        .translation();
    let wanted = target.lock().unwrap().unwrap().base_from_tcp.translation();
    assert!((reached - wanted).norm() < 0.005, "{reached:?} {wanted:?}");
    assert!(run.still);
    check_recording(&run.report);

    // When every alternative is refused too, the episode says so and the arm stays put.
    let run = run_episode_with(
        "ranked_refused",
        6,
        |_| {
            Box::new(Ranked {
                ranked: vec![far(2.5), far(3.0)],
                next: 0,
            })
        },
        |_| {},
    );
    assert_eq!(run.report.outcome, Outcome::PlanFailed);
    assert_eq!(run.report.steps, 0);
    assert!(
        run.report.detail.contains("1 next-ranked"),
        "{}",
        run.report.detail
    );
    assert!(run.still);
    check_recording(&run.report);
}

/// Passes the learned policy's keyframes on, at most `limit` of them, and keeps a copy.
struct Limited {
    inner: LearnedPolicy,
    limit: usize,
    emitted: Arc<Mutex<Vec<Keyframe>>>,
}

impl KeyframeSource for Limited {
    fn next_keyframe(
        &mut self,
        obs: &equact::episode::Observation<'_>,
    ) -> anyhow::Result<Option<Keyframe>> {
        let mut emitted = self.emitted.lock().unwrap();
        if emitted.len() >= self.limit {
            return Ok(None);
        }
        assert_eq!(obs.cloud.frame, cell_types::FrameId::Base);
        let k = self.inner.next_keyframe(obs)?;
        emitted.extend(k);
        Ok(k)
    }

    fn name(&self) -> &str {
        self.inner.name()
    }
}

/// `equact run --policy learned` plumbing: the network (tiny, random weights: what it
/// predicts is arbitrary) gets the fused cloud, its keyframes go to the planner and the
/// arm, the recording holds them, and the arm ends still.
#[test]
fn learned_policy_drives_the_loop_and_the_recording_checks_out() {
    let emitted = Arc::new(Mutex::new(Vec::new()));
    let copy = emitted.clone();
    let run = run_episode_with(
        "learned",
        2,
        move |_| {
            let cfg = CellConfig::simulated().unwrap();
            let net = for_cell(PolicyConfig::tiny(), &cfg);
            let policy = Policy::random(net, 7).unwrap();
            let inner = LearnedPolicy::new(policy, InstructionEmbedding::random(1), &cfg).unwrap();
            Box::new(Limited {
                inner,
                limit: 2,
                emitted: copy,
            })
        },
        |_| {},
    );
    let r = &run.report;
    eprintln!(
        "learned episode: {:?} after {} steps: {}",
        r.outcome, r.steps, r.detail
    );
    assert!(
        matches!(
            r.outcome,
            Outcome::TaskNotDone | Outcome::PlanFailed | Outcome::Success
        ),
        "{:?}: {}",
        r.outcome,
        r.detail
    );
    let emitted = emitted.lock().unwrap();
    assert!(!emitted.is_empty(), "the network predicted nothing");
    // Every predicted keyframe lies in the network's gripper box (the cell's workspace).
    let cfg = CellConfig::simulated().unwrap();
    for k in emitted.iter() {
        let t = k.base_from_tcp.translation();
        for (i, v) in [t.x, t.y, t.z].into_iter().enumerate() {
            assert!(
                v >= cfg.workspace.min[i] - 0.02 && v <= cfg.workspace.max[i] + 1e-9,
                "{t:?}"
            );
        }
    }
    // Executed steps are the keyframes that were planned; a plan failure stops at one.
    let expected_steps = if r.outcome == Outcome::PlanFailed {
        emitted.len() - 1
    } else {
        emitted.len()
    };
    assert_eq!(r.steps, expected_steps, "{}", r.detail);
    assert_eq!(
        r.counts.get("/keyframes").copied(),
        Some(emitted.len() as u64)
    );
    assert!(run.still);
    check_recording(r);
}

/// Keep the unused-import lint honest for helpers shared across tests.
#[allow(dead_code)]
fn _uses(_: PathBuf, _: &dyn KeyframeSource) {}

/// Taking the second pipe link when the first was asked for cannot be undone (a released
/// link falls to the table): the episode ends `task_lost` at the keyframe that pulled it,
/// instead of running on to the keyframe limit, and says which part moved.
#[test]
fn pulling_the_wrong_link_ends_the_episode_as_lost() {
    let first = TaskKind::parse("disassemble_pipe/first_link").unwrap();
    let second = TaskKind::parse("disassemble_pipe/second_link").unwrap();
    let seed = 3;
    let run = run_task_episode(
        first,
        "lost",
        seed,
        |task| {
            // The same scene under the other instruction: the second link's expert.
            let other = TaskInstance::sample(second, seed, task.table_height);
            Box::new(ScriptedExpert::new(other.expert_keyframes()))
        },
        |_| {},
    );
    let r = &run.report;
    assert_eq!(r.outcome, Outcome::TaskLost, "{}", r.detail);
    // Above the link, around it, pulled off: lost there, before the expert's last keyframe.
    assert_eq!(r.steps, 3, "{}", r.detail);
    assert!(
        r.detail.contains("second") && r.detail.contains("in place"),
        "{}",
        r.detail
    );
    assert!(run.still);
    check_recording(r);
}
