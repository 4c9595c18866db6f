//! The learned EquAct policy as a [`KeyframeSource`]: the episode loop hands it the fused,
//! sampled cloud, the arm's TCP pose and the gripper state; it answers with the network's
//! keyframe (`equact run --policy learned`).
//!
//! The network never says "done": the episode ends when the task's success test passes, on
//! a fault, or after [`crate::episode::MAX_KEYFRAMES`], as in the keyframe-policy
//! literature's evaluation.

use std::path::Path;

use anyhow::Context;
use cell_types::config::CellConfig;
use cell_types::{Base, Keyframe, Tcp, Transform};
use policy::predict::{GripperPose, InstructionEmbedding, Policy, PolicyConfig};

use crate::episode::{robot_model, KeyframeSource, Observation};

/// Fingertip opening above which the gripper counts as open for the network's input (m):
/// the 2F-85 opens to 0.085; anything holding an object or closed is well below.
const OPEN_WIDTH_M: f64 = 0.08;

/// The learned policy: the network, the instruction's embedding, and the arm's forward
/// kinematics (the network reads the current TCP pose).
pub struct LearnedPolicy {
    policy: Policy,
    instruction: InstructionEmbedding,
    model: planner::model::RobotModel,
    /// The episode's seed; prediction k runs with `episode_seed + k`.
    episode_seed: u64,
    predictions: u64,
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
        Ok(Self {
            episode_seed: policy.seed,
            policy,
            instruction,
            model,
            predictions: 0,
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
        Self::load_with(network, weights, instruction, cfg, seed)
    }

    /// Loads the weights file, with an instruction embedding already in memory.
    pub fn load_with(
        network: PolicyConfig,
        weights: &Path,
        instruction: InstructionEmbedding,
        cfg: &CellConfig,
        seed: u64,
    ) -> anyhow::Result<Self> {
        let policy_cfg = for_cell(network, cfg);
        let mut policy = Policy::load(policy_cfg, weights).with_context(|| {
            format!(
                "loading the EquAct weights {} (they must match the chosen --network size)",
                weights.display()
            )
        })?;
        policy.seed = seed;
        Self::new(policy, instruction, cfg)
    }

    /// The instruction the next predictions follow.
    pub fn set_instruction(&mut self, instruction: InstructionEmbedding) {
        self.instruction = instruction;
    }

    /// Seeds the next episode's predictions (each prediction adds its index).
    pub fn set_seed(&mut self, seed: u64) {
        self.episode_seed = seed;
        self.predictions = 0;
    }
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
        let keyframe = self
            .policy
            .predict(obs.cloud, &gripper, &self.instruction)
            .context("the EquAct network could not predict a keyframe")?;
        Ok(Some(keyframe))
    }

    fn name(&self) -> &str {
        "learned"
    }
}
