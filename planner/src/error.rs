//! The planner's one error type: every way a model load, an IK query or a plan can fail.

use thiserror::Error;

/// Why the planner could not load a model, solve IK, or plan a motion.
#[derive(Debug, Error, Clone, PartialEq)]
#[non_exhaustive]
pub enum PlanError {
    /// The URDF text could not be parsed.
    #[error("URDF could not be parsed: {message}; check the file against the URDF schema")]
    UrdfParse {
        /// The parser's message.
        message: String,
    },
    /// The URDF lacks a link or joint the model needs, or has one of the wrong kind.
    #[error("URDF: {what}; the model needs a serial chain base_link -> ... -> tcp with six revolute joints")]
    UrdfStructure {
        /// What is missing or wrong.
        what: String,
    },
    /// The URDF's kinematics disagree with the DH parameters the analytic IK uses.
    #[error("URDF forward kinematics differ from the DH parameters by {error_m} m at q = {q:?}; regenerate the URDF from the same UrParams")]
    ModelMismatch {
        /// The configuration where they differ.
        q: [f64; 6],
        /// The position difference (m).
        error_m: f64,
    },
    /// A value that must be finite was NaN or infinite.
    #[error("{what} is not finite; check the source of this value")]
    NotFinite {
        /// Which value.
        what: &'static str,
    },
    /// A joint value lies outside its limits.
    #[error("joint {joint} = {value} rad is outside its limits [{lower}, {upper}]; bring the arm inside its limits first")]
    JointLimit {
        /// Joint index (0 = base).
        joint: usize,
        /// The value.
        value: f64,
        /// Lower limit.
        lower: f64,
        /// Upper limit.
        upper: f64,
    },
    /// No joint configuration reaches the pose.
    #[error("pose unreachable: {reason}; move the target closer to the arm")]
    Unreachable {
        /// Which geometric condition failed.
        reason: &'static str,
    },
    /// The pose is at a kinematic singularity where the solutions are not isolated.
    #[error("pose is singular ({kind}): infinitely many solutions; perturb the target orientation slightly")]
    Singular {
        /// Which singularity.
        kind: &'static str,
    },
    /// Every IK solution is outside the joint limits.
    #[error("all {solutions} IK solutions are outside the joint limits")]
    AllSolutionsOutOfLimits {
        /// How many analytic solutions there were.
        solutions: usize,
    },
    /// Every IK solution within limits is in collision.
    #[error("all {solutions} IK solutions are in collision; first: {first}")]
    AllSolutionsInCollision {
        /// How many were tried.
        solutions: usize,
        /// What touches what for the first solution.
        first: Contact,
    },
    /// The start configuration is in collision.
    #[error("start configuration is in collision: {contact}; move the arm clear before planning")]
    StartInCollision {
        /// What touches what.
        contact: Contact,
    },
    /// The path search found nothing within its budget.
    #[error("no collision-free path found within {iterations} iterations; the goal may be enclosed, or raise the budget")]
    NoPath {
        /// Iterations spent.
        iterations: usize,
    },
    /// Planner limits are not usable.
    #[error("planner limit {what} = {value} must be positive and finite")]
    BadLimit {
        /// Which limit.
        what: &'static str,
        /// The value.
        value: f64,
    },
    /// The time parameterization failed.
    #[error("time parameterization failed on segment {segment}: {message}")]
    Timing {
        /// Segment index.
        segment: usize,
        /// The generator's message.
        message: String,
    },
    /// The sampled trajectory breaks a limit.
    #[error(
        "trajectory sample {sample} joint {joint}: {quantity} = {value} exceeds the limit {limit}"
    )]
    LimitViolated {
        /// Sample index.
        sample: usize,
        /// Joint index.
        joint: usize,
        /// position, velocity, acceleration or jerk.
        quantity: &'static str,
        /// The value.
        value: f64,
        /// The limit (with tolerance).
        limit: f64,
    },
    /// The executed trajectory collides when re-checked densely.
    #[error("trajectory collides at t = {t} s: {contact}")]
    TrajectoryCollides {
        /// Time of the first collision (s).
        t: f64,
        /// What touches what.
        contact: Contact,
    },
    /// The executed trajectory touches something when re-checked with the exact link shapes.
    #[error("trajectory collides at t = {t} s in the exact re-check: {contact}")]
    ExactCollision {
        /// Time of the first contact (s).
        t: f64,
        /// Which link touches what.
        contact: ExactContact,
    },
    /// The exact geometry library cannot test a pair of shapes.
    #[error("exact check: parry cannot test {what}")]
    ExactUnsupported {
        /// The shape pair.
        what: String,
    },
    /// A trajectory could not be built from the samples.
    #[error("trajectory could not be built: {message}")]
    Trajectory {
        /// The cell-types error message.
        message: String,
    },
    /// A world could not be built.
    #[error("world: {what}")]
    BadWorld {
        /// What was wrong.
        what: String,
    },
}

/// What touches what: a robot link and either another link or the environment.
#[derive(Debug, Clone, PartialEq)]
pub struct Contact {
    /// The robot link in contact.
    pub link: &'static str,
    /// The other side: another link's name, "cloud", or a static obstacle's name.
    pub other: String,
}

impl std::fmt::Display for Contact {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "link {} touches {}", self.link, self.other)
    }
}

/// What a robot link touches in the exact (parry) check.
#[derive(Debug, Clone, PartialEq)]
pub enum ExactOther {
    /// Another link of the same robot (self-collision).
    Link(&'static str),
    /// A static obstacle, by name.
    Obstacle(String),
    /// A point of the observed cloud (base frame, m).
    CloudPoint([f64; 3]),
}

/// A contact found by the exact check: a robot link and what it touches.
#[derive(Debug, Clone, PartialEq)]
pub struct ExactContact {
    /// The robot link in contact.
    pub link: &'static str,
    /// The other side.
    pub other: ExactOther,
}

impl std::fmt::Display for ExactContact {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "link {} touches ", self.link)?;
        match &self.other {
            ExactOther::Link(l) => write!(f, "link {l} (self-collision)"),
            ExactOther::Obstacle(n) => write!(f, "obstacle {n}"),
            ExactOther::CloudPoint(p) => {
                write!(f, "cloud point ({:.4}, {:.4}, {:.4}) m", p[0], p[1], p[2])
            }
        }
    }
}
