//! `equact plot`: pictures of a recorded episode. Per executed motion, the planned joint
//! position, velocity, acceleration and jerk with the limits drawn, and the tracking error of
//! the measured joints against the plan with its bound; per step, the fused cloud with the
//! robot and the keyframes from above and from the side. Reads truncated recordings up to
//! their last complete chunk. Drawn with our own small raster ([`canvas`]) and the `png`
//! crate: no plotting library, no system fonts.

pub mod canvas;

use std::path::{Path, PathBuf};

use base64::Engine;
use cell_types::{Joints, JOINT_COUNT};
use nalgebra::Point3;
use serde_json::Value;

use canvas::{Canvas, Colour, Panel, BLACK, GREY, JOINT_COLOURS, RED, WHITE};

/// Why a recording could not be plotted.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The recording could not be read.
    #[error("plot: cannot read {path}: {detail}")]
    Read {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        detail: String,
    },
    /// A message did not have the fields its schema promises.
    #[error("plot: a {topic} message is malformed ({detail}); was it written by equact run?")]
    BadMessage {
        /// The topic.
        topic: &'static str,
        /// What was missing.
        detail: String,
    },
    /// Nothing to draw.
    #[error("plot: {0} holds no planned trajectory and no fused cloud; nothing to draw")]
    Empty(PathBuf),
    /// A picture could not be written.
    #[error("plot: cannot write {path}: {detail}")]
    Write {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        detail: String,
    },
}

/// One planned motion as recorded on `/trajectory/joints`.
#[derive(Clone, Debug, Default)]
pub struct PlannedMotion {
    /// Keyframe index.
    pub step: usize,
    /// Log time of the execution start (ns).
    pub start_ns: u64,
    /// Sample period (s).
    pub period: f64,
    /// Positions, velocities and accelerations per sample.
    pub samples: Vec<[Joints; 3]>,
    /// Joint velocity, acceleration and jerk limits.
    pub limits: [Joints; 3],
    /// Tracking error bound (rad).
    pub tracking_bound: f64,
}

/// A recorded keyframe.
#[derive(Clone, Debug)]
pub struct RecordedKeyframe {
    /// TCP position in the base frame.
    pub position: Point3<f64>,
    /// Gripper open at the keyframe.
    pub open: bool,
}

/// A recorded fused cloud: log time (ns), points, optional colours.
pub type RecordedCloud = (u64, Vec<Point3<f32>>, Option<Vec<Colour>>);

/// What `equact plot` draws, read from a recording.
#[derive(Clone, Debug, Default)]
pub struct EpisodeData {
    /// Planned motions in order.
    pub motions: Vec<PlannedMotion>,
    /// Measured joint positions with their log times (ns).
    pub joints: Vec<(u64, Joints)>,
    /// Recorded TCP positions with their log times (ns).
    pub tcp: Vec<(u64, Point3<f64>)>,
    /// Fused clouds, one per step.
    pub clouds: Vec<RecordedCloud>,
    /// Keyframes in order.
    pub keyframes: Vec<RecordedKeyframe>,
}

fn bad(topic: &'static str, detail: impl Into<String>) -> PlotError {
    PlotError::BadMessage {
        topic,
        detail: detail.into(),
    }
}

fn joints_of(v: &Value, topic: &'static str) -> Result<Joints, PlotError> {
    let a = v
        .as_array()
        .filter(|a| a.len() == JOINT_COUNT)
        .ok_or_else(|| bad(topic, "expected 6 joint values"))?;
    let mut out = [0.0; JOINT_COUNT];
    for (o, x) in out.iter_mut().zip(a) {
        *o = x
            .as_f64()
            .ok_or_else(|| bad(topic, "a joint value is not a number"))?;
    }
    Ok(out)
}

fn vec3(v: &Value) -> Option<Point3<f64>> {
    Some(Point3::new(
        v["x"].as_f64()?,
        v["y"].as_f64()?,
        v["z"].as_f64()?,
    ))
}

impl EpisodeData {
    /// Reads what the plots need from recording bytes (complete chunks of a truncated file
    /// included).
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, PlotError> {
        let mut data = Self::default();
        let options = enumset::enum_set!(mcap::read::Options::IgnoreEndMagic);
        let stream =
            mcap::MessageStream::new_with_options(bytes, options).map_err(|e| PlotError::Read {
                path: PathBuf::new(),
                detail: e.to_string(),
            })?;
        // A truncated file ends with a read error: keep what came before it.
        for message in stream.map_while(Result::ok) {
            let topic = message.channel.topic.as_str();
            if !matches!(
                topic,
                "/trajectory/joints" | "/joint_states" | "/tf" | "/cloud/fused" | "/keyframes"
            ) {
                continue;
            }
            let v: Value = serde_json::from_slice(&message.data).map_err(|e| PlotError::Read {
                path: PathBuf::new(),
                detail: format!("{topic}: {e}"),
            })?;
            let t = message.log_time;
            match topic {
                "/trajectory/joints" => data.motions.push(Self::motion(&v, t)?),
                "/joint_states" => {
                    let js = v["joints"]
                        .as_array()
                        .ok_or_else(|| bad("/joint_states", "no joints"))?;
                    let positions: Vec<Value> = js.iter().map(|j| j["position"].clone()).collect();
                    data.joints
                        .push((t, joints_of(&Value::Array(positions), "/joint_states")?));
                }
                "/tf" => {
                    for tf in v["transforms"].as_array().into_iter().flatten() {
                        if tf["child_frame_id"] == "tcp" {
                            if let Some(p) = vec3(&tf["translation"]) {
                                data.tcp.push((t, p));
                            }
                        }
                    }
                }
                "/cloud/fused" => data.clouds.push(Self::cloud(&v, t)?),
                _ => {
                    for e in v["entities"].as_array().into_iter().flatten() {
                        let open = e["metadata"]
                            .as_array()
                            .into_iter()
                            .flatten()
                            .any(|m| m["key"] == "gripper_open" && m["value"] == "true");
                        let position = vec3(&e["arrows"][0]["pose"]["position"])
                            .ok_or_else(|| bad("/keyframes", "no arrow pose"))?;
                        data.keyframes.push(RecordedKeyframe { position, open });
                    }
                }
            }
        }
        Ok(data)
    }

    fn motion(v: &Value, t: u64) -> Result<PlannedMotion, PlotError> {
        const TOPIC: &str = "/trajectory/joints";
        let rows = |key: &str| -> Result<Vec<Joints>, PlotError> {
            v[key]
                .as_array()
                .ok_or_else(|| bad(TOPIC, format!("no {key}")))?
                .iter()
                .map(|r| joints_of(r, TOPIC))
                .collect()
        };
        let (p, vel, acc) = (
            rows("positions")?,
            rows("velocities")?,
            rows("accelerations")?,
        );
        if p.len() != vel.len() || p.len() != acc.len() || p.len() < 2 {
            return Err(bad(TOPIC, "sample arrays differ in length or hold < 2"));
        }
        let period = v["period_s"]
            .as_f64()
            .filter(|p| *p > 0.0)
            .ok_or_else(|| bad(TOPIC, "no positive period_s"))?;
        Ok(PlannedMotion {
            step: v["step"].as_u64().unwrap_or(0) as usize,
            start_ns: t,
            period,
            samples: (0..p.len()).map(|i| [p[i], vel[i], acc[i]]).collect(),
            limits: [
                joints_of(&v["max_velocity"], TOPIC)?,
                joints_of(&v["max_acceleration"], TOPIC)?,
                joints_of(&v["max_jerk"], TOPIC)?,
            ],
            tracking_bound: v["tracking_bound"].as_f64().unwrap_or(f64::NAN),
        })
    }

    #[allow(clippy::type_complexity)]
    fn cloud(v: &Value, t: u64) -> Result<(u64, Vec<Point3<f32>>, Option<Vec<Colour>>), PlotError> {
        const TOPIC: &str = "/cloud/fused";
        let stride = v["point_stride"]
            .as_u64()
            .filter(|s| *s >= 12)
            .ok_or_else(|| bad(TOPIC, "point_stride < 12"))? as usize;
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(v["data"].as_str().unwrap_or(""))
            .map_err(|e| bad(TOPIC, format!("data is not base64: {e}")))?;
        let has_rgb = v["fields"]
            .as_array()
            .is_some_and(|f| f.iter().any(|f| f["name"] == "red"))
            && stride >= 15;
        let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        let mut points = Vec::with_capacity(bytes.len() / stride);
        let mut rgb = Vec::new();
        for p in bytes.chunks_exact(stride) {
            points.push(Point3::new(f(&p[0..4]), f(&p[4..8]), f(&p[8..12])));
            if has_rgb {
                rgb.push([p[12], p[13], p[14]]);
            }
        }
        Ok((t, points, has_rgb.then_some(rgb)))
    }
}

/// Jerk of a sampled motion: the backward difference of its accelerations.
pub fn jerk(samples: &[[Joints; 3]], period: f64) -> Vec<Joints> {
    let mut out = vec![[0.0; JOINT_COUNT]; samples.len()];
    for i in 1..samples.len() {
        for j in 0..JOINT_COUNT {
            out[i][j] = (samples[i][2][j] - samples[i - 1][2][j]) / period;
        }
    }
    out
}

/// Tracking error of measured joints against a plan: the plan's start is aligned to the
/// measurements by the delay (0 to 2 s, one period steps) that minimises the mean error,
/// since the recording logs the plan before the driver uploads its program. Returns
/// (seconds since the aligned start, max-abs joint error) for every measurement during the
/// motion.
pub fn tracking_error(motion: &PlannedMotion, measured: &[(u64, Joints)]) -> Vec<(f64, f64)> {
    if motion.samples.len() < 2 || motion.period.is_nan() || motion.period <= 0.0 {
        return Vec::new();
    }
    let duration = motion.period * (motion.samples.len() - 1) as f64;
    let planned_at = |tau: f64| -> Joints {
        let x = (tau / motion.period).clamp(0.0, (motion.samples.len() - 1) as f64);
        let i = (x.floor() as usize).min(motion.samples.len() - 2);
        let f = x - i as f64;
        let (a, b) = (motion.samples[i][0], motion.samples[i + 1][0]);
        std::array::from_fn(|j| a[j] + f * (b[j] - a[j]))
    };
    let window: Vec<(f64, Joints)> = measured
        .iter()
        .filter(|(t, _)| *t >= motion.start_ns)
        .map(|(t, q)| ((t - motion.start_ns) as f64 * 1e-9, *q))
        .take_while(|(tau, _)| *tau <= duration + 2.5)
        .collect();
    let errors_at = |delay: f64| -> Vec<(f64, f64)> {
        window
            .iter()
            .map(|(tau, q)| (tau - delay, q))
            .filter(|(tau, _)| *tau >= 0.0 && *tau <= duration)
            .map(|(tau, q)| {
                let p = planned_at(tau);
                let e = (0..JOINT_COUNT)
                    .map(|j| (q[j] - p[j]).abs())
                    .fold(0.0, f64::max);
                (tau, e)
            })
            .collect()
    };
    let mean = |e: &[(f64, f64)]| e.iter().map(|x| x.1).sum::<f64>() / e.len().max(1) as f64;
    let best_of = |delays: &mut dyn Iterator<Item = f64>| {
        delays
            .map(|d| (d, errors_at(d)))
            .filter(|(_, e)| e.len() * 2 >= motion.samples.len())
            .min_by(|a, b| mean(&a.1).total_cmp(&mean(&b.1)))
    };
    // Coarse: whole periods up to 2 s; fine: 1/16 period around the best coarse delay (the
    // measurements' phase is arbitrary).
    let steps = (2.0 / motion.period) as usize;
    let Some((coarse, _)) = best_of(&mut (0..=steps).map(|k| k as f64 * motion.period)) else {
        return Vec::new();
    };
    best_of(
        &mut (-16..=16)
            .map(|k| coarse + f64::from(k) * motion.period / 16.0)
            .filter(|d| *d >= 0.0),
    )
    .map(|(_, e)| e)
    .unwrap_or_default()
}

fn range_of(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !lo.is_finite() {
        return (-1.0, 1.0);
    }
    let pad = ((hi - lo) * 0.08).max(1e-6);
    (lo - pad, hi + pad)
}

/// Draws one motion: position, velocity, acceleration, jerk (limits dashed red) and the
/// tracking error (bound dashed red).
pub fn motion_figure(motion: &PlannedMotion, measured: &[(u64, Joints)]) -> Canvas {
    const W: i64 = 1000;
    const ROW: i64 = 170;
    const LEFT: i64 = 70;
    let mut c = Canvas::new(W as u32, (5 * ROW + 40) as u32, WHITE);
    let ts: Vec<f64> = (0..motion.samples.len())
        .map(|i| i as f64 * motion.period)
        .collect();
    let duration = ts.last().copied().unwrap_or(1.0).max(motion.period);
    c.text(
        LEFT,
        8,
        &format!(
            "keyframe {}: {} samples, {:.2} s (joints 1-6 coloured)",
            motion.step,
            motion.samples.len(),
            duration
        ),
        BLACK,
    );
    let j = jerk(&motion.samples, motion.period);
    let quantity = |k: usize, i: usize, joint: usize| -> f64 {
        if k < 3 {
            motion.samples[i][k][joint]
        } else {
            j[i][joint]
        }
    };
    let names = [
        "position (rad)",
        "velocity (rad/s)",
        "acceleration (rad/s2)",
        "jerk (rad/s3)",
    ];
    for (k, name) in names.iter().enumerate() {
        let limit = (k > 0).then(|| motion.limits[k - 1]);
        let values = (0..motion.samples.len())
            .flat_map(|i| (0..JOINT_COUNT).map(move |jt| (i, jt)))
            .map(|(i, jt)| quantity(k, i, jt));
        // The limits of the joints that move most set the scale, so that both the data and
        // the nearest limit show.
        let peak = (0..JOINT_COUNT)
            .max_by(|a, b| {
                let m = |jt: usize| {
                    (0..motion.samples.len())
                        .map(|i| quantity(k, i, jt).abs())
                        .fold(0.0, f64::max)
                };
                m(*a).total_cmp(&m(*b))
            })
            .unwrap_or(0);
        let with_limit: Vec<f64> = values
            .chain(limit.iter().flat_map(|l| [l[peak], -l[peak]]))
            .collect();
        let panel = Panel {
            left: LEFT,
            top: 30 + k as i64 * ROW,
            width: W - LEFT - 20,
            height: ROW - 30,
            x: (0.0, duration),
            y: range_of(with_limit.into_iter()),
        };
        draw_axes(&mut c, &panel, name);
        if let Some(l) = limit {
            for lj in l {
                for sign in [1.0, -1.0] {
                    let (_, y) = panel.map(0.0, sign * lj);
                    if y > panel.top && y < panel.top + panel.height {
                        c.dashed_hline(panel.left, panel.left + panel.width, y, RED);
                    }
                }
            }
        }
        for (jt, colour) in JOINT_COLOURS.iter().enumerate() {
            let ys: Vec<f64> = (0..motion.samples.len())
                .map(|i| quantity(k, i, jt))
                .collect();
            panel.series(&mut c, &ts, &ys, *colour);
        }
    }
    let errors = tracking_error(motion, measured);
    let panel = Panel {
        left: LEFT,
        top: 30 + 4 * ROW,
        width: W - LEFT - 20,
        height: ROW - 30,
        x: (0.0, duration),
        y: (
            0.0,
            range_of(
                errors
                    .iter()
                    .map(|e| e.1)
                    .chain(std::iter::once(motion.tracking_bound)),
            )
            .1,
        ),
    };
    draw_axes(&mut c, &panel, "tracking error, max over joints (rad)");
    if motion.tracking_bound.is_finite() {
        let (_, y) = panel.map(0.0, motion.tracking_bound);
        c.dashed_hline(panel.left, panel.left + panel.width, y, RED);
    }
    let (ex, ey): (Vec<f64>, Vec<f64>) = errors.into_iter().unzip();
    panel.series(&mut c, &ex, &ey, BLACK);
    c
}

fn draw_axes(c: &mut Canvas, panel: &Panel, title: &str) {
    let (_, zero) = panel.map(0.0, 0.0);
    if zero > panel.top && zero < panel.top + panel.height {
        c.line(
            (panel.left, zero),
            (panel.left + panel.width, zero),
            GREY,
            1,
        );
    }
    panel.frame(c);
    c.text(panel.left + 4, panel.top - 12, title, BLACK);
    c.text(2, panel.top, &format!("{:>8.2}", panel.y.1), BLACK);
    c.text(
        2,
        panel.top + panel.height - 8,
        &format!("{:>8.2}", panel.y.0),
        BLACK,
    );
    c.text(
        panel.left + panel.width - 56,
        panel.top + panel.height + 3,
        &format!("{:.2} s", panel.x.1),
        BLACK,
    );
}

/// Draws one step: the cloud (own colours, else by height), the robot's links at the time of
/// the cloud as a dark polyline, and the keyframes so far (green open, red closed), from
/// above (x right, y up) and from the side (x right, z up).
pub fn scene_figure(data: &EpisodeData, step: usize) -> Option<Canvas> {
    let (t, points, rgb) = data.clouds.get(step)?;
    const SIZE: i64 = 560;
    let mut c = Canvas::new((2 * SIZE + 30) as u32, (SIZE + 40) as u32, WHITE);
    c.text(
        10,
        8,
        &format!(
            "step {step}: {} points; left: top view (x, y), right: side view (x, z)",
            points.len()
        ),
        BLACK,
    );
    // The robot at the cloud's time: the last measured joints before it.
    let q = data
        .joints
        .iter()
        .take_while(|(tj, _)| tj <= t)
        .last()
        .or(data.joints.first())
        .map(|(_, q)| *q);
    let mut robot: Vec<Point3<f64>> = q
        .map(|q| {
            planner::kinematics::UR5
                .link_frames(&q)
                .iter()
                .map(|f| Point3::from(f.translation.vector))
                .collect()
        })
        .unwrap_or_default();
    if let Some((_, p)) = data.tcp.iter().take_while(|(tt, _)| tt <= t).last() {
        robot.push(*p);
    }
    let keyframes = &data.keyframes[..data.keyframes.len().min(step + 1)];
    let all = points
        .iter()
        .map(|p| p.cast::<f64>())
        .chain(robot.iter().copied())
        .chain(keyframes.iter().map(|k| k.position));
    let (mut lo, mut hi) = (
        Point3::new(f64::MAX, f64::MAX, f64::MAX),
        Point3::new(f64::MIN, f64::MIN, f64::MIN),
    );
    for p in all {
        lo = lo.inf(&p);
        hi = hi.sup(&p);
    }
    if lo.x > hi.x {
        return None;
    }
    let span = (hi - lo).max().max(0.1) * 1.1;
    let mid = nalgebra::center(&lo, &hi);
    let (z_lo, z_hi) = (lo.z, hi.z.max(lo.z + 1e-6));
    for (view, axes) in [(0usize, (0usize, 1usize)), (1, (0, 2))] {
        let panel = Panel {
            left: 10 + view as i64 * (SIZE + 10),
            top: 30,
            width: SIZE,
            height: SIZE,
            x: (mid[axes.0] - span / 2.0, mid[axes.0] + span / 2.0),
            y: (mid[axes.1] - span / 2.0, mid[axes.1] + span / 2.0),
        };
        panel.frame(&mut c);
        // Far points first so that near ones stay on top: sort by the hidden axis.
        let hidden = 3 - axes.0 - axes.1;
        let mut order: Vec<usize> = (0..points.len()).collect();
        let sign = if view == 0 { 1.0 } else { -1.0 };
        order.sort_by(|a, b| (sign * points[*a][hidden]).total_cmp(&(sign * points[*b][hidden])));
        for i in order {
            let p = points[i].cast::<f64>();
            let colour = match rgb {
                Some(rgb) => rgb[i],
                None => height_colour((p.z - z_lo) / (z_hi - z_lo)),
            };
            let (x, y) = panel.map(p[axes.0], p[axes.1]);
            c.dot(x, y, 1, colour);
        }
        for w in robot.windows(2) {
            c.line(
                panel.map(w[0][axes.0], w[0][axes.1]),
                panel.map(w[1][axes.0], w[1][axes.1]),
                [20, 20, 90],
                5,
            );
        }
        for k in keyframes {
            let (x, y) = panel.map(k.position[axes.0], k.position[axes.1]);
            let colour = if k.open { [20, 170, 40] } else { RED };
            c.line((x - 8, y - 8), (x + 8, y + 8), colour, 3);
            c.line((x - 8, y + 8), (x + 8, y - 8), colour, 3);
        }
    }
    Some(c)
}

fn height_colour(f: f64) -> Colour {
    let f = f.clamp(0.0, 1.0);
    [
        (60.0 + 180.0 * f) as u8,
        (90.0 + 80.0 * (1.0 - (2.0 * f - 1.0).abs())) as u8,
        (220.0 - 180.0 * f) as u8,
    ]
}

/// Reads `recording` and writes `motion_NN.png` per planned motion and `scene_NN.png` per
/// step into `out` (created if missing); returns the files written.
pub fn plot_file(recording: &Path, out: &Path) -> Result<Vec<PathBuf>, PlotError> {
    let bytes = std::fs::read(recording).map_err(|e| PlotError::Read {
        path: recording.to_path_buf(),
        detail: e.to_string(),
    })?;
    let data = EpisodeData::from_bytes(&bytes).map_err(|e| match e {
        PlotError::Read { detail, .. } => PlotError::Read {
            path: recording.to_path_buf(),
            detail,
        },
        other => other,
    })?;
    if data.motions.is_empty() && data.clouds.is_empty() {
        return Err(PlotError::Empty(recording.to_path_buf()));
    }
    std::fs::create_dir_all(out).map_err(|e| PlotError::Write {
        path: out.to_path_buf(),
        detail: e.to_string(),
    })?;
    let mut written = Vec::new();
    for motion in &data.motions {
        let path = out.join(format!("motion_{:02}.png", motion.step));
        motion_figure(motion, &data.joints).save_png(&path)?;
        written.push(path);
    }
    for step in 0..data.clouds.len() {
        if let Some(fig) = scene_figure(&data, step) {
            let path = out.join(format!("scene_{step:02}.png"));
            fig.save_png(&path)?;
            written.push(path);
        }
    }
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cubic_motion(period: f64, n: usize) -> PlannedMotion {
        // q = t^3 on joint 0: v = 3t^2, a = 6t, jerk = 6.
        let samples = (0..n)
            .map(|i| {
                let t = i as f64 * period;
                let mut p = [[0.0; JOINT_COUNT]; 3];
                p[0][0] = t.powi(3);
                p[1][0] = 3.0 * t * t;
                p[2][0] = 6.0 * t;
                p
            })
            .collect();
        PlannedMotion {
            step: 0,
            start_ns: 1_000_000_000,
            period,
            samples,
            limits: [[1.0; 6], [2.0; 6], [10.0; 6]],
            tracking_bound: 0.05,
        }
    }

    #[test]
    fn a_degenerate_motion_has_no_tracking_error_and_still_draws() {
        let mut m = cubic_motion(0.008, 1);
        assert!(tracking_error(&m, &[(m.start_ns, [0.0; 6])]).is_empty());
        m.samples.clear();
        let c = motion_figure(&m, &[]);
        assert_eq!(c.width, 1000);
    }

    #[test]
    fn jerk_of_a_cubic_is_constant() {
        let m = cubic_motion(0.008, 100);
        let j = jerk(&m.samples, m.period);
        assert!(j[1..].iter().all(|r| (r[0] - 6.0).abs() < 1e-9));
    }

    #[test]
    fn tracking_error_finds_the_start_delay_and_the_offset() {
        let m = cubic_motion(0.008, 126);
        // Measured: the plan started 0.3 s after it was logged, with 0.01 rad offset on
        // joint 2.
        let measured: Vec<(u64, Joints)> = (0..300)
            .map(|i| {
                let t = i as f64 * 0.008;
                let tau = (t - 0.3).clamp(0.0, 1.0);
                let mut q = [0.0; JOINT_COUNT];
                q[0] = tau.powi(3);
                q[2] = 0.01;
                (m.start_ns + (t * 1e9) as u64, q)
            })
            .collect();
        let e = tracking_error(&m, &measured);
        assert!(e.len() > 100);
        assert!(e.iter().all(|(_, x)| (x - 0.01).abs() < 1e-3), "{e:?}");
    }

    #[test]
    fn motion_figure_draws_limits_and_curves() {
        let m = cubic_motion(0.008, 126);
        let c = motion_figure(&m, &[]);
        let red = c.pixels.iter().filter(|p| **p == RED).count();
        let joint0 = c.pixels.iter().filter(|p| **p == JOINT_COLOURS[0]).count();
        assert!(red > 100, "{red} limit pixels");
        assert!(joint0 > 300, "{joint0} curve pixels");
    }
}
