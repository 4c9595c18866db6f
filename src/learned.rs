//! The learned EquAct policy as a [`KeyframeSource`]: the episode loop hands it the fused,
//! sampled cloud, the arm's TCP pose and the gripper state; it answers with the network's
//! keyframe (`equact run --policy learned`).
//!
//! Two rules turn the network's answer into what the cell executes (both are documented
//! where they are defined): a short move of a held object is planned through the cloud
//! ([`HELD_MOVE_THROUGH_CLOUD_M`]), and a keyframe the planner refuses is replaced by the
//! next-ranked translation candidates ([`LearnedPolicy::set_alternatives`]).
//!
//! The network never says "done": the episode ends when the task's success test passes, on
//! a fault, or after [`crate::episode::MAX_KEYFRAMES`], as in the keyframe-policy
//! literature's evaluation.

use std::path::Path;

use anyhow::Context;
use cell_types::config::{CellConfig, PerceptionSection};
use cell_types::{Base, Keyframe, Tcp, Transform};
use policy::predict::{
    GripperPose, InstructionEmbedding, Policy, PolicyConfig, SceneEncoding, TranslationCandidate,
};

use crate::episode::{robot_model, KeyframeSource, Observation};

/// Fingertip opening above which the gripper counts as open for the network's input (m):
/// the 2F-85 opens to 0.085; anything holding an object or closed is well below.
const OPEN_WIDTH_M: f64 = 0.08;

/// Next-ranked keyframes offered by default when the planner refuses a prediction.
pub const DEFAULT_ALTERNATIVES: usize = 8;

/// Longest move (m, TCP) that is planned without the observed cloud while the gripper holds
/// an object. EquAct predicts no "ignore collisions" flag, but the moves that need it are
/// the short extraction and insertion moves of a held object (the demonstrations' pulls of
/// 7–8 cm and the roll's 5 cm descent over the spindle), where the carried object's own
/// points lie where the gripper goes; the table and fixed obstacles still count.
pub const HELD_MOVE_THROUGH_CLOUD_M: f64 = 0.09;

/// How far apart (m) the translations of the next-ranked keyframes are, from each other and
/// from the prediction: the finest sampling level's runners-up lie within millimetres of
/// its best, and a keyframe the planner refuses is seldom planned a few millimetres over.
pub const ALTERNATIVE_SEPARATION_M: f64 = 0.01;

/// How far each ranked keyframe is also tried moved back along its approach axis (m): a
/// grasp predicted a centimetre too deep puts the palm on the object or the fingertips on
/// the table, and the same grasp a little shallower still closes on the object.
pub const BACK_OFFS_M: [f64; 3] = [0.0, 0.01, 0.02];

/// The last prediction's encoded scene and its remaining translation candidates.
struct LastPrediction {
    scene: SceneEncoding,
    /// Best first; the first is the predicted keyframe's.
    candidates: Vec<TranslationCandidate>,
    /// The next alternative: candidate `next / BACK_OFFS_M.len()` moved back by
    /// `BACK_OFFS_M[next % BACK_OFFS_M.len()]` (0, the prediction itself, is already used).
    next: usize,
    /// The keyframe of the candidate being backed off, by candidate index.
    current: (usize, Keyframe),
    /// The observation's TCP position and whether the gripper held an object.
    tcp: nalgebra::Vector3<f64>,
    holding: bool,
}

impl LastPrediction {
    /// The keyframe with its collision flag for this observation.
    fn with_collision_flag(&self, keyframe: Keyframe) -> Keyframe {
        with_collision_flag(keyframe, &self.tcp, self.holding)
    }
}

/// The keyframe moved back by `distance` (m) along its approach axis (the TCP z).
pub fn backed_off(mut keyframe: Keyframe, distance: f64) -> Keyframe {
    let approach = keyframe.base_from_tcp.isometry().rotation * nalgebra::Vector3::z();
    let p = keyframe.base_from_tcp.translation() - approach * distance;
    keyframe.base_from_tcp = Transform::from_parts(p, keyframe.base_from_tcp.isometry().rotation);
    keyframe
}

/// Marks a short move of a held object as planned without the cloud
/// ([`HELD_MOVE_THROUGH_CLOUD_M`]); any other keyframe is planned against it.
pub fn with_collision_flag(
    mut keyframe: Keyframe,
    tcp: &nalgebra::Vector3<f64>,
    holding: bool,
) -> Keyframe {
    let moved = (keyframe.base_from_tcp.translation() - tcp).norm();
    keyframe.ignore_collisions = holding && moved <= HELD_MOVE_THROUGH_CLOUD_M;
    keyframe
}

/// The learned policy: the network, the instruction's embedding, and the arm's forward
/// kinematics (the network reads the current TCP pose).
pub struct LearnedPolicy {
    policy: Policy,
    instruction: InstructionEmbedding,
    model: planner::model::RobotModel,
    /// The episode's seed; prediction k runs with `episode_seed + k`.
    episode_seed: u64,
    predictions: u64,
    /// How many next-ranked keyframes to offer per observation.
    alternatives: usize,
    last: Option<LastPrediction>,
}

impl LearnedPolicy {
    /// Wraps a built policy; `cfg` names the arm whose forward kinematics give the TCP.
    pub fn new(
        policy: Policy,
        instruction: InstructionEmbedding,
        cfg: &CellConfig,
    ) -> anyhow::Result<Self> {
        let model =
            robot_model(cfg).context("building the arm model for the policy's TCP input")?;
        check_instruction_width(&policy, &instruction)?;
        Ok(Self {
            episode_seed: policy.seed,
            policy,
            instruction,
            model,
            predictions: 0,
            alternatives: DEFAULT_ALTERNATIVES,
            last: None,
        })
    }

    /// Loads the weights file and the instruction embedding file, with the network
    /// configuration `network` adapted to the cell's workspace box and table.
    pub fn load(
        network: PolicyConfig,
        weights: &Path,
        instruction: &Path,
        cfg: &CellConfig,
        seed: u64,
    ) -> anyhow::Result<Self> {
        let instruction = InstructionEmbedding::from_file(instruction).with_context(|| {
            format!(
                "reading the instruction embedding {} (safetensors, one F32 tensor: tokens x width)",
                instruction.display()
            )
        })?;
        Self::load_with(network, Some(weights), instruction, cfg, seed)
    }

    /// Loads the weights file `weights`, or the model compiled into the binary when `None`
    /// (`policy::builtin`: the cpu network trained on the simulated cell's demonstrations),
    /// with an instruction embedding already in memory and the network configuration
    /// `network` adapted to the cell's workspace box and table.
    pub fn load_with(
        network: PolicyConfig,
        weights: Option<&Path>,
        instruction: InstructionEmbedding,
        cfg: &CellConfig,
        seed: u64,
    ) -> anyhow::Result<Self> {
        check_cell_perception(&network, cfg)?;
        let mut policy = load_network(network, weights, cfg)?;
        policy.seed = seed;
        Self::new(policy, instruction, cfg)
    }

    /// The instruction the next predictions follow.
    pub fn set_instruction(&mut self, instruction: InstructionEmbedding) {
        self.instruction = instruction;
    }

    /// How many next-ranked keyframes to offer when the planner refuses a prediction (the
    /// best translations of every sampling level at least [`ALTERNATIVE_SEPARATION_M`]
    /// apart, each with the rotation and open heads' answer there), each also tried moved back by [`BACK_OFFS_M`]; 0 executes the
    /// network's argmax or nothing, as the paper evaluates.
    pub fn set_alternatives(&mut self, n: usize) {
        self.alternatives = n;
    }

    /// Threads of each prediction (see `policy::parallel`; the keyframes do not depend on
    /// it). 1 by default: on a real cell the UR driver's threads need a free core.
    pub fn set_threads(&mut self, threads: usize) {
        self.policy.set_threads(threads);
    }

    /// Seeds the next episode's predictions (each prediction adds its index).
    pub fn set_seed(&mut self, seed: u64) {
        self.episode_seed = seed;
        self.predictions = 0;
        self.last = None;
    }
}

/// Refuses an instruction embedding of another token width than the network reads, when
/// the policy is loaded rather than at its first prediction mid-episode.
fn check_instruction_width(
    policy: &Policy,
    instruction: &InstructionEmbedding,
) -> anyhow::Result<()> {
    let want = policy.model().language().token_dim();
    if instruction.dim() != want {
        anyhow::bail!(
            "the instruction embedding has {} values per token, the network reads {want} \
             (384: MiniLM, `--minilm` or the built-in embeddings; 512: CLIP files): give the \
             embedding the weights were trained with",
            instruction.dim()
        );
    }
    Ok(())
}

/// The network `network`, adapted to the cell's workspace box and table, with the weights
/// file `weights`, or the model compiled into the binary when `None` (`policy::builtin`).
pub fn load_network(
    network: PolicyConfig,
    weights: Option<&Path>,
    cfg: &CellConfig,
) -> anyhow::Result<Policy> {
    let policy_cfg = for_cell(network, cfg);
    match weights {
        Some(weights) => Policy::load(policy_cfg, weights).with_context(|| {
            format!(
                "loading the EquAct weights {} (they must match the chosen --network size)",
                weights.display()
            )
        }),
        None => policy::builtin::policy(policy_cfg).with_context(|| {
            format!(
                "loading the built-in EquAct weights ({})",
                policy::builtin::WEIGHTS_PATH
            )
        }),
    }
}

/// Refuses a network whose input the clouds of `perception` (of the cell or of the
/// demonstrations named by `source`) cannot give: more points than they hold (the network
/// would fail on the first keyframe), or points near the gripper on clouds that were not
/// sampled densely there (it would see a held object through a dozen points instead of the
/// many it was trained on, and place it less precisely without saying so). `fix` says what
/// to change for the second; the first names `[perception] points`.
pub fn check_perception(
    network: &PolicyConfig,
    perception: &PerceptionSection,
    source: &str,
    fix: &str,
) -> anyhow::Result<()> {
    if network.n_points > perception.points {
        anyhow::bail!(
            "the network reads {} points, but {source} sampled {} ([perception] points): \
             sample at least as many, or use a network that reads fewer (--points)",
            network.n_points,
            perception.points
        );
    }
    let (wanted, radius) = (network.n_near_gripper, network.near_gripper_radius);
    let (fused, fused_radius) = (perception.gripper_points, perception.gripper_radius_m);
    if wanted > 0 && (wanted > fused || fused_radius < radius) {
        anyhow::bail!(
            "the network samples {wanted} of its points within {radius} m of the gripper, but \
             {source} sampled {fused} within {fused_radius} m there: {fix}"
        );
    }
    Ok(())
}

/// The `perception` setting a training run records: `None` for EquAct's plain sampling
/// (so plain runs record what they did before the setting existed).
pub fn recorded_perception(perception: &PerceptionSection) -> Option<PerceptionSection> {
    (*perception != PerceptionSection::default()).then(|| perception.clone())
}

/// How the clouds a network last trained on were sampled: the `perception` of the last run
/// in its training history (`policy::weights::TRAINING_KEY`); EquAct's plain sampling when
/// that run records none (plain runs, runs from before the setting, the built-in model).
pub fn trained_perception(history: &[serde_json::Value]) -> anyhow::Result<PerceptionSection> {
    match history.last().and_then(|run| run.get("perception")) {
        None | Some(serde_json::Value::Null) => Ok(PerceptionSection::default()),
        Some(p) => serde_json::from_value(p.clone())
            .context("the weights' training history records an unreadable perception setting"),
    }
}

/// [`trained_perception`] of the weights file `weights` (`None`: the built-in model), read
/// from its header.
pub fn weights_perception(weights: Option<&Path>) -> anyhow::Result<PerceptionSection> {
    let Some(path) = weights else {
        return Ok(PerceptionSection::default());
    };
    let runs = policy::weights::Weights::header_only(path)
        .and_then(|header| header.training_history())
        .with_context(|| format!("reading the weights file {}", path.display()))?;
    trained_perception(&runs)
}

/// A note when `now` (the clouds of `source`) samples otherwise than the network's
/// demonstrations were (`trained`): the network then sees another kind of cloud than it
/// learned from (e.g. the table top instead of the objects), which costs precision
/// silently. `None` when they agree.
pub fn perception_note(
    trained: &PerceptionSection,
    now: &PerceptionSection,
    source: &str,
) -> Option<String> {
    (trained != now).then(|| {
        format!(
            "note: the network's demonstrations were sampled with [perception] {trained}, \
             the clouds of {source} with {now}: it sees other clouds than it learned from; \
             set [perception] as the demonstrations were recorded"
        )
    })
}

/// [`check_perception`] against a cell's own fusion.
pub fn check_cell_perception(network: &PolicyConfig, cfg: &CellConfig) -> anyhow::Result<()> {
    check_perception(
        network,
        &cfg.perception,
        "this cell's fusion",
        "set [perception] gripper_points and gripper_radius_m in the cell configuration to \
         what the network's demonstrations were recorded with",
    )
}

/// The network configuration with the crop box, focus box and table of this cell.
pub fn for_cell(mut network: PolicyConfig, cfg: &CellConfig) -> PolicyConfig {
    let ws = &cfg.workspace;
    network.workspace_bounds = [ws.min, ws.max];
    network.table_height = ws.table_height;
    // The gripper may go from just above the table to the top of the workspace.
    network.gripper_bounds = [[ws.min[0], ws.min[1], ws.table_height - 0.01], ws.max];
    network
}

impl KeyframeSource for LearnedPolicy {
    fn next_keyframe(&mut self, obs: &Observation<'_>) -> anyhow::Result<Option<Keyframe>> {
        let base_from_tcp: Transform<Base, Tcp> = self.model.fk_tcp(&obs.joints.position);
        let gripper = GripperPose {
            base_from_tcp,
            open: obs.gripper.width_m > OPEN_WIDTH_M,
        };
        // A new seed per prediction: the translation sampling is random, but each episode
        // is reproducible from its seed.
        self.policy.seed = self.episode_seed.wrapping_add(self.predictions);
        self.predictions += 1;
        let prediction = self
            .policy
            .predict_detailed(obs.cloud, &gripper, &self.instruction)
            .context("the EquAct network could not predict a keyframe")?;
        let candidates =
            prediction.distinct_candidates(self.alternatives + 1, ALTERNATIVE_SEPARATION_M);
        let last = LastPrediction {
            scene: prediction.scene,
            candidates,
            next: 1,
            current: (0, prediction.keyframe),
            tcp: base_from_tcp.translation(),
            holding: obs.gripper.holds_object(),
        };
        let keyframe = last.with_collision_flag(prediction.keyframe);
        self.last = Some(last);
        Ok(Some(keyframe))
    }

    fn alternative(&mut self) -> anyhow::Result<Option<Keyframe>> {
        let Some(last) = self.last.as_mut() else {
            return Ok(None);
        };
        let (c, b) = (last.next / BACK_OFFS_M.len(), last.next % BACK_OFFS_M.len());
        if c > self.alternatives {
            return Ok(None);
        }
        let Some(candidate) = last.candidates.get(c) else {
            return Ok(None);
        };
        last.next += 1;
        if last.current.0 != c {
            let at = self
                .policy
                .keyframe_at(&last.scene, &candidate.position)
                .context("the EquAct network could not rank another keyframe")?;
            last.current = (c, at.keyframe);
        }
        let keyframe = backed_off(last.current.1, BACK_OFFS_M[b]);
        Ok(Some(last.with_collision_flag(keyframe)))
    }

    fn name(&self) -> &str {
        "learned"
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn at(x: f64) -> Keyframe {
        Keyframe::new(
            Transform::from_xyz_rpy([x, 0.0, 0.2], [std::f64::consts::PI, 0.0, 0.0]),
            false,
            false,
        )
        .unwrap()
    }

    /// Why loading the built-in weights as `network` on `cell` fails.
    fn load_error(network: &PolicyConfig, cell: &CellConfig) -> String {
        let instruction = policy::builtin::instruction("pick up the peach").unwrap();
        LearnedPolicy::load_with(network.clone(), None, instruction, cell, 0)
            .err()
            .unwrap()
            .to_string()
    }

    #[test]
    fn a_network_sampling_near_the_gripper_needs_the_cells_fusion_to() {
        let mut cell = CellConfig::simulated().unwrap();
        let network = policy::builtin::config().with_near_gripper_points(128);
        let err = load_error(&network, &cell);
        assert!(err.contains("gripper_points"), "{err}");
        assert!(check_cell_perception(&policy::builtin::config(), &cell).is_ok());
        cell.perception.gripper_points = 256;
        assert!(check_cell_perception(&network, &cell).is_ok());
        cell.perception.gripper_radius_m = 0.04;
        assert!(check_cell_perception(&network, &cell).is_err());
    }

    #[test]
    fn the_last_training_run_says_how_its_clouds_were_sampled() {
        let raised = PerceptionSection {
            points: 1280,
            focus_above_table_m: Some(0.01),
            ..PerceptionSection::default()
        };
        // No history (the built-in model) or a last run without the setting: plain.
        assert_eq!(
            trained_perception(&[]).unwrap(),
            PerceptionSection::default()
        );
        let plain_run = serde_json::json!({"steps": 10, "lr": 1e-4});
        let raised_run = serde_json::json!({"steps": 20, "perception": raised});
        let history = [plain_run.clone(), raised_run.clone()];
        assert_eq!(trained_perception(&history).unwrap(), raised);
        // A later plain fine-tune is what the network last adapted to.
        let history = [raised_run, plain_run];
        assert_eq!(
            trained_perception(&history).unwrap(),
            PerceptionSection::default()
        );
        let bad = [serde_json::json!({"perception": {"points": "many"}})];
        assert!(trained_perception(&bad).is_err());
        assert_eq!(
            weights_perception(None).unwrap(),
            PerceptionSection::default()
        );
        // The note names both settings; agreeing settings give none.
        let note =
            perception_note(&raised, &PerceptionSection::default(), "this cell's fusion").unwrap();
        assert!(note.contains("focus_above_table_m = 0.01"), "{note}");
        assert!(
            note.contains("the clouds of this cell's fusion with points = 2048"),
            "{note}"
        );
        assert!(perception_note(&raised, &raised, "x").is_none());
        // A dataset records its setting only when it is not the plain one.
        assert_eq!(recorded_perception(&PerceptionSection::default()), None);
        assert_eq!(recorded_perception(&raised), Some(raised));
    }

    #[test]
    fn a_network_reading_more_points_than_the_cell_samples_is_refused_at_load() {
        let mut cell = CellConfig::simulated().unwrap();
        cell.perception.points = 512;
        let network = policy::builtin::config();
        assert_eq!(network.n_points, 1024);
        let err = load_error(&network, &cell);
        assert!(err.contains("[perception] points"), "{err}");
        assert!(err.contains("1024") && err.contains("512"), "{err}");
        cell.perception.points = 1024;
        assert!(check_cell_perception(&network, &cell).is_ok());
    }

    #[test]
    fn backing_off_moves_along_the_approach_axis_only() {
        // Pointing down (roll π): the approach axis is −z of the base, so backing off rises.
        let k = at(0.5);
        let b = backed_off(k, 0.02);
        let d = b.base_from_tcp.translation() - k.base_from_tcp.translation();
        assert!((d - Vector3::new(0.0, 0.0, 0.02)).norm() < 1e-12, "{d:?}");
        assert_eq!(
            b.base_from_tcp.isometry().rotation,
            k.base_from_tcp.isometry().rotation
        );
        assert_eq!(b.gripper_open, k.gripper_open);
        assert_eq!(backed_off(k, 0.0), k);
    }

    #[test]
    fn only_short_moves_of_a_held_object_go_through_the_cloud() {
        let tcp = Vector3::new(0.5, 0.0, 0.2);
        assert!(with_collision_flag(at(0.55), &tcp, true).ignore_collisions);
        assert!(
            with_collision_flag(at(0.5 + HELD_MOVE_THROUGH_CLOUD_M), &tcp, true).ignore_collisions
        );
        assert!(
            !with_collision_flag(at(0.5 + HELD_MOVE_THROUGH_CLOUD_M + 1e-3), &tcp, true)
                .ignore_collisions
        );
        // Not holding: every move is planned against the cloud, however short.
        assert!(!with_collision_flag(at(0.51), &tcp, false).ignore_collisions);
        // A flag already set is recomputed, not kept.
        let mut k = at(0.8);
        k.ignore_collisions = true;
        assert!(!with_collision_flag(k, &tcp, true).ignore_collisions);
    }

    #[test]
    fn an_instruction_of_another_token_width_is_refused_when_loading() {
        #![allow(clippy::unwrap_used)]
        let cfg = CellConfig::simulated().unwrap();
        let text = "pick up the peach";
        let minilm = policy::builtin::instruction(text).unwrap();
        // The built-in model reads MiniLM's 384-wide tokens.
        assert!(
            LearnedPolicy::load_with(policy::builtin::config(), None, minilm.clone(), &cfg, 0)
                .is_ok()
        );
        let clip = InstructionEmbedding::random(0);
        let err = LearnedPolicy::load_with(policy::builtin::config(), None, clip, &cfg, 0)
            .err()
            .unwrap()
            .to_string();
        assert!(
            err.contains("has 512 values per token, the network reads 384"),
            "{err}"
        );
        // And a CLIP-width network refuses MiniLM's.
        let tiny = Policy::random(for_cell(PolicyConfig::tiny(), &cfg), 1).unwrap();
        let err = LearnedPolicy::new(tiny, minilm, &cfg)
            .err()
            .unwrap()
            .to_string();
        assert!(
            err.contains("has 384 values per token, the network reads 512"),
            "{err}"
        );
    }
}
