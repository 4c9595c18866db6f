//! `equact perceive`: render the three simulated D455 cameras of the default cell, fuse
//! them (calibration::fusion) and write the clouds as PLY plus pictures of them as PNG
//! (issue 7 item 5). With `--config`, it captures one frameset from each of the real cell's
//! D455s instead (`firmware_iface::realsense`, serials and modes from the config) and fuses
//! them with the config's calibration file; the arm is not read, so it is not cropped out.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use calibration::fusion::{Capsule, FusionParams, FusionPipeline};
use calibration::view::{splat, write_ply};
use calibration::CellCalibration;
use calibration::{DepthMode, Intrinsics};
use cell_types::{CameraFrame, Image, Rgb};
use firmware_iface::realsense;
use hil_sim::depth_camera::{default_rig, render_rig, rig_calibration};
use hil_sim::scene::{robot_capsules, Scene, HOME_Q};
use nalgebra::Point3;

/// Arguments of `equact perceive`.
#[derive(clap::Args, Debug)]
pub struct PerceiveArgs {
    /// Folder for fused.ply, sampled.ply, top.png and perspective.png (created if missing).
    #[arg(long, default_value = "perceive_out")]
    pub out: PathBuf,
    /// Seed of the simulated sensor noise and of the sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Depth mode of the simulated cameras: 848x480, 1280x720 or 640x480 (with --config the
    /// config's modes are used).
    #[arg(long, default_value = "848x480")]
    pub mode: String,
    /// Also write each camera's raw depth as a 16-bit PNG (millimetres).
    #[arg(long)]
    pub depth_png: bool,
    /// A real cell's configuration: capture from its D455 cameras (needs librealsense2).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// With --config: framesets to drop after each camera starts, while auto-exposure
    /// settles.
    #[arg(long, default_value_t = 30)]
    pub warmup: u32,
}

fn parse_mode(s: &str) -> anyhow::Result<DepthMode> {
    Ok(match s {
        "848x480" => DepthMode::Wvga848x480,
        "1280x720" => DepthMode::Hd1280x720,
        "640x480" => DepthMode::Vga640x480,
        other => anyhow::bail!("unknown depth mode {other:?}; use 848x480, 1280x720 or 640x480"),
    })
}

/// Writes an RGB image as PNG.
pub fn write_png_rgb(path: &Path, img: &Image<Rgb>) -> anyhow::Result<()> {
    let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = png::Encoder::new(BufWriter::new(file), img.width, img.height);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header()?;
    w.write_image_data(img.data.as_flattened())?;
    Ok(())
}

fn write_png_depth(path: &Path, img: &Image<u16>) -> anyhow::Result<()> {
    let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut enc = png::Encoder::new(BufWriter::new(file), img.width, img.height);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Sixteen);
    let mut w = enc.write_header()?;
    // PNG stores 16-bit samples big-endian.
    let bytes: Vec<u8> = img.data.iter().flat_map(|v| v.to_be_bytes()).collect();
    w.write_image_data(&bytes)?;
    Ok(())
}

/// Frames, camera names, the calibration to fuse with, the fusion parameters and the robot
/// capsules to crop.
type Captured = (
    Vec<CameraFrame>,
    Vec<String>,
    CellCalibration,
    FusionParams,
    Vec<Capsule>,
);

/// Renders the simulated rig of the default cell and fuses it with the built-in simulated
/// cell's fusion settings (those of `equact run`).
fn simulated(args: &PerceiveArgs) -> anyhow::Result<Captured> {
    let mode = parse_mode(&args.mode)?;
    let scene = Scene::default_cell();
    let geometry = scene.build()?;
    let mut rig = default_rig(args.seed);
    for c in &mut rig {
        c.intrinsics = Intrinsics::d455_depth(mode);
    }
    let frames = render_rig(&rig, &geometry, 0, Duration::ZERO)?;
    // Fused as the simulated episodes fuse: the built-in cell's workspace and sampling.
    let params = equact::episode::fusion_params(&super::config::load(None)?, args.seed);
    Ok((
        frames,
        rig.iter().map(|c| c.name.clone()).collect(),
        rig_calibration(&rig),
        params,
        robot_capsules(&HOME_Q, 0.085),
    ))
}

/// Captures one frameset from each configured D455 (camera `i` is the config's `i`-th).
fn real(args: &PerceiveArgs, path: &Path) -> anyhow::Result<Captured> {
    let cfg = super::config::load(Some(&path.to_path_buf()))?;
    if cfg.calibration.file.is_empty() {
        anyhow::bail!(
            "{} names no calibration.file: calibrate the cameras (`equact calibrate`) first",
            path.display()
        );
    }
    let dir = super::config::config_dir(Some(&path.to_path_buf()));
    let cal_path = dir.join(&cfg.calibration.file);
    let calibration = calibration::read_calibration_toml(&cal_path)
        .with_context(|| format!("reading the calibration {}", cal_path.display()))?;
    let (lib, version) = realsense::library()?;
    eprintln!(
        "librealsense {}.{}.{} from {}",
        version / 10000,
        version / 100 % 100,
        version % 100,
        lib.display()
    );
    let frames = equact::real_cell::capture_frames(
        &cfg,
        args.warmup,
        &mut equact::real_cell::open_configured,
    )?;
    Ok((
        frames,
        cfg.cameras.iter().map(|c| c.name.clone()).collect(),
        calibration,
        equact::episode::fusion_params(&cfg, args.seed),
        Vec::new(),
    ))
}

/// Runs `equact perceive`.
pub fn run(args: PerceiveArgs) -> anyhow::Result<()> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating the output folder {}", args.out.display()))?;
    let (frames, names, calibration, params, robot) = match &args.config {
        None => simulated(&args)?,
        Some(path) => real(&args, path)?,
    };
    if args.depth_png {
        for (name, f) in names.iter().zip(&frames) {
            write_png_depth(&args.out.join(format!("depth_{name}.png")), &f.depth.raw)?;
        }
    }
    let pipe = FusionPipeline::new(calibration, params)?;
    let fused = pipe.fuse(&frames, &robot)?;
    for (name, cloud) in [("fused.ply", &fused.dense), ("sampled.ply", &fused.sampled)] {
        let path = args.out.join(name);
        let file = File::create(&path).with_context(|| format!("creating {}", path.display()))?;
        write_ply(cloud, BufWriter::new(file))?;
    }
    let view = Intrinsics::d455_depth(DepthMode::Hd1280x720);
    let top = splat(
        &fused.dense,
        &view,
        Point3::new(0.57, 0.0, 0.95),
        Point3::new(0.57, 0.0, 0.0),
        1,
    );
    write_png_rgb(&args.out.join("top.png"), &top)?;
    let persp = splat(
        &fused.dense,
        &view,
        Point3::new(1.5, -0.7, 0.8),
        Point3::new(0.57, 0.0, 0.0),
        1,
    );
    write_png_rgb(&args.out.join("perspective.png"), &persp)?;
    println!(
        "{}",
        serde_json::json!({
            "out": args.out.display().to_string(),
            "stats": fused.stats,
            "dense_points": fused.dense.len(),
            "sampled_points": fused.sampled.len(),
        })
    );
    Ok(())
}
