//! The Intel RealSense D455 capture backend (issue 7 item 4): [`RealSenseCamera`]
//! implements [`DepthCamera`] on librealsense2, loaded at run time.
//!
//! # Loading librealsense
//!
//! The crate does not link librealsense: the library is opened with `dlopen` (crate
//! `libloading`) the first time a camera is opened or listed, from
//! `EQUACT_LIBREALSENSE=/path/to/librealsense2.so` when set, else `librealsense2.so.2`, then
//! `librealsense2.so` on the dynamic linker's path. A missing library is the typed error
//! [`RealSenseError::LibraryNotFound`], which says how to install it. Only the C functions
//! this module uses are looked up (see the private `ffi` module, the crate's only `unsafe`).
//!
//! Because nothing is needed at build time, the backend is always built: no cargo feature,
//! so CI compiles, lints and tests it on every run, and `equact check` / `equact perceive`
//! on the real cell work from the default build. Its cost to a build without cameras is one
//! small pure-Rust dependency (`libloading`) and this module.
//!
//! # Threads
//!
//! librealsense runs its own threads: a device watcher for the context, and USB transfer
//! and frame-dispatch threads per streaming sensor (a playback device has a reader thread).
//! The streaming threads stop when the pipeline stops ([`RealSenseCamera`]'s drop). The
//! process keeps one librealsense context for live devices, created on first use and never
//! deleted, so its device watcher runs until the process exits, and the library stays
//! loaded; a recording plays in a context of its own, deleted with its camera. Closing a
//! recording waits for its reader thread after the stop (librealsense hands
//! the playback's own stop to that thread without waiting, and deleting the device under
//! it corrupted the heap). One recording plays at a time: librealsense 2.59 crashed
//! (SIGSEGV, "pure virtual method called") playing two at once in one process.
//!
//! # Frames
//!
//! Depth (Z16) and the left infrared image (Y8, infrared index 1, which shares the depth
//! intrinsics) stream at the requested mode and rate. Depth is converted to millimetres
//! from the device's depth units (each frame carries them; the D455's default is 0.001 m,
//! where the raw values are copied unchanged); a value that would not fit in u16
//! millimetres becomes 0 ("no depth"). With [`RealSenseCamera::open_with_colour`] (or a
//! recording with colour) the RGB8 colour stream is resampled onto the depth pixels by
//! librealsense's `align` processing block (on the capturing thread), which is what
//! `CameraFrame::colour` means; otherwise `colour` is `None`.

mod ffi;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use cell_types::config::DepthMode;
use cell_types::{CameraFrame, DepthImage, Image, Rgb};
use thiserror::Error;

use crate::camera::{CameraError, DepthCamera};

pub use ffi::{preload_global, LIBRARY_ENV};
use ffi::{Align, Context, Pipeline, Rs2Error, Source, StreamRequest};

/// The depth unit frames are delivered in (m per count): millimetres.
pub const DEPTH_SCALE_MM: f32 = 0.001;

/// What went wrong with librealsense or a RealSense device.
#[derive(Debug, Error, Clone, PartialEq)]
#[non_exhaustive]
pub enum RealSenseError {
    /// The shared library could not be loaded.
    #[error(
        "librealsense2 not found (tried {tried}: {why}): install librealsense2 (Debian/Ubuntu: \
         librealsense2-dev from Intel's apt repo) or set EQUACT_LIBREALSENSE=/path/to/librealsense2.so"
    )]
    LibraryNotFound {
        /// The paths or names tried.
        tried: String,
        /// What the dynamic loader said.
        why: String,
    },
    /// The library lacks a function this backend needs.
    #[error("{library} has no {symbol} ({why}): it is not librealsense2 2.50 or newer; point EQUACT_LIBREALSENSE at librealsense2.so")]
    MissingSymbol {
        /// The library loaded.
        library: String,
        /// The missing function.
        symbol: &'static str,
        /// What the loader said.
        why: String,
    },
    /// The library's major version is not 2.
    #[error("{library} is librealsense {major}.x; this backend needs 2.x (2.50 or newer)")]
    Version {
        /// The library loaded.
        library: String,
        /// Its major version.
        major: i32,
    },
    /// librealsense was already loaded from another file in this process.
    #[error("librealsense2 is already loaded from {loaded}; cannot also load {requested} in one process")]
    AlreadyLoaded {
        /// The file in use.
        loaded: String,
        /// The file asked for.
        requested: String,
    },
    /// A librealsense call failed.
    #[error("librealsense failed while {doing}: {function}: {message}")]
    Call {
        /// What the backend was doing.
        doing: String,
        /// The C function that failed.
        function: String,
        /// librealsense's message.
        message: String,
    },
    /// No device with the serial is connected.
    #[error("no D455 with serial {serial}; connected: {}; check the USB 3 cable and the serial in the config (`rs-enumerate-devices` lists them)", list_or_none(.connected))]
    NotConnected {
        /// The serial asked for.
        serial: String,
        /// The serials (and names) found.
        connected: Vec<String>,
    },
    /// The device would not stream the requested mode.
    #[error("camera {serial} cannot stream depth + IR at {width}x{height} {fps} fps: {message}; use a mode and rate the D455 offers (848x480, 640x480 or 1280x720 at 5, 15 or 30 fps) on a USB 3 port")]
    Mode {
        /// The device or recording.
        serial: String,
        /// Requested width.
        width: u32,
        /// Requested height.
        height: u32,
        /// Requested rate.
        fps: u32,
        /// librealsense's message.
        message: String,
    },
    /// No frame within the timeout.
    #[error("camera {camera}: no frame within {timeout_ms} ms")]
    Timeout {
        /// The camera id.
        camera: u8,
        /// The timeout (ms).
        timeout_ms: u64,
    },
    /// Another recording is already playing in this process.
    #[error("cannot play {path}: another recording is playing in this process (librealsense crashes playing two at once); drop the other camera first")]
    PlaybackBusy {
        /// The recording asked for.
        path: String,
    },
    /// A frameset lacked a stream or had an unexpected layout.
    #[error("camera {camera}: bad frame: {what}")]
    BadFrame {
        /// The camera id.
        camera: u8,
        /// What was wrong.
        what: String,
    },
}

/// The error mapper for one step of a capture.
fn call(doing: &'static str) -> impl Fn(Rs2Error) -> RealSenseError {
    move |e| RealSenseError::call(&e, doing)
}

fn list_or_none(v: &[String]) -> String {
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

impl RealSenseError {
    fn call(e: &Rs2Error, doing: &str) -> Self {
        Self::Call {
            doing: doing.to_string(),
            function: e.function.clone(),
            message: e.message.clone(),
        }
    }
}

/// The trait's error for a backend error: timeouts stay timeouts, everything else carries
/// the whole message (librealsense's included).
fn camera_error(camera: u8, e: RealSenseError) -> CameraError {
    match e {
        RealSenseError::Timeout { camera, timeout_ms } => {
            CameraError::Timeout { camera, timeout_ms }
        }
        other => CameraError::Device {
            camera,
            message: other.to_string(),
        },
    }
}

/// Lens distortion model of a stream (`rs2_distortion`).
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum DistortionModel {
    /// Rectified (depth, IR).
    None,
    /// Modified Brown-Conrady.
    ModifiedBrownConrady,
    /// Inverse Brown-Conrady (the D455 colour stream).
    InverseBrownConrady,
    /// F-theta fisheye.
    FTheta,
    /// Brown-Conrady.
    BrownConrady,
    /// Kannala-Brandt 4.
    KannalaBrandt4,
    /// A value this backend does not know.
    Other(i32),
}

impl DistortionModel {
    fn from_raw(v: i32) -> Self {
        match v {
            0 => Self::None,
            1 => Self::ModifiedBrownConrady,
            2 => Self::InverseBrownConrady,
            3 => Self::FTheta,
            4 => Self::BrownConrady,
            5 => Self::KannalaBrandt4,
            o => Self::Other(o),
        }
    }
}

/// Intrinsics of one stream as the device (or recording) reports them.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct StreamIntrinsics {
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Focal length x (px).
    pub fx: f64,
    /// Focal length y (px).
    pub fy: f64,
    /// Principal point x (px, librealsense's pixel-centre convention).
    pub ppx: f64,
    /// Principal point y (px).
    pub ppy: f64,
    /// Distortion model.
    pub model: DistortionModel,
    /// Distortion coefficients `[k1, k2, p1, p2, k3]`.
    pub coeffs: [f64; 5],
}

impl StreamIntrinsics {
    fn from_raw(i: &ffi::RsIntrinsics) -> Self {
        Self {
            width: u32::try_from(i.width).unwrap_or(0),
            height: u32::try_from(i.height).unwrap_or(0),
            fx: f64::from(i.fx),
            fy: f64::from(i.fy),
            ppx: f64::from(i.ppx),
            ppy: f64::from(i.ppy),
            model: DistortionModel::from_raw(i.model),
            coeffs: i.coeffs.map(f64::from),
        }
    }
}

/// A connected RealSense device.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DeviceInfo {
    /// Serial number.
    pub serial: String,
    /// Product name (e.g. "Intel RealSense D455").
    pub name: String,
}

/// Loads librealsense2 (see the module docs for the search order) and returns the file it
/// came from and its API version (`major * 10000 + minor * 100 + patch`).
pub fn library() -> Result<(PathBuf, i32), RealSenseError> {
    ffi::load(None)
}

/// Loads librealsense2 from `path` for this process, before any camera is opened (tests
/// and tools that ship their own copy); fails if another file is already loaded.
pub fn load_library(path: &Path) -> Result<(PathBuf, i32), RealSenseError> {
    ffi::load(Some(path))
}

/// The RealSense devices connected now.
pub fn connected_devices() -> Result<Vec<DeviceInfo>, RealSenseError> {
    let ctx = Context::live()?;
    list(ctx)
}

fn list(ctx: &Context) -> Result<Vec<DeviceInfo>, RealSenseError> {
    Ok(ctx
        .devices()
        .map_err(|e| RealSenseError::call(&e, "listing devices"))?
        .into_iter()
        .map(|(serial, name)| DeviceInfo { serial, name })
        .collect())
}

/// A streaming D455 (or a recording of one) as a [`DepthCamera`]; dropping it stops the
/// pipeline.
pub struct RealSenseCamera {
    id: u8,
    source: String,
    /// Resamples colour onto depth when a colour stream runs; dropped before the pipeline.
    align: Option<Align>,
    colour: Option<StreamIntrinsics>,
    pipeline: Pipeline,
    depth: StreamIntrinsics,
    ir: Option<StreamIntrinsics>,
    fps: u32,
    timeout_ms: u32,
    /// Held by a recording's camera; released after the pipeline stops (field order).
    _playback: Option<PlaybackSlot>,
}

/// Whether a recording is playing in this process.
static PLAYBACK_ACTIVE: AtomicBool = AtomicBool::new(false);

/// The one playback slot: librealsense 2.59 crashed (SIGSEGV, "pure virtual method
/// called") when two recordings played at once in one process, so a second is refused.
struct PlaybackSlot;

impl PlaybackSlot {
    fn take(path: &Path) -> Result<Self, RealSenseError> {
        PLAYBACK_ACTIVE
            .compare_exchange(false, true, Ordering::AcqRel, Ordering::Acquire)
            .map(|_| PlaybackSlot)
            .map_err(|_| RealSenseError::PlaybackBusy {
                path: path.display().to_string(),
            })
    }
}

impl Drop for PlaybackSlot {
    fn drop(&mut self) {
        PLAYBACK_ACTIVE.store(false, Ordering::Release);
    }
}

impl std::fmt::Debug for RealSenseCamera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RealSenseCamera")
            .field("id", &self.id)
            .field("source", &self.source)
            .field("depth", &self.depth)
            .field("ir", &self.ir)
            .field("fps", &self.fps)
            .finish_non_exhaustive()
    }
}

/// The default wait for a frameset: the first one after a start can take a second or two
/// while auto-exposure settles.
const DEFAULT_TIMEOUT_MS: u32 = 5000;

impl RealSenseCamera {
    /// Opens the connected device with `serial` and starts depth (Z16) and left IR (Y8) at
    /// `mode` and `fps`.
    pub fn open(id: u8, serial: &str, mode: DepthMode, fps: u32) -> Result<Self, RealSenseError> {
        Self::open_streams(id, serial, mode, fps, false)
    }

    /// [`open`](Self::open), plus colour (RGB8, same size and rate) aligned to depth pixel
    /// for pixel by librealsense's `align` block.
    pub fn open_with_colour(
        id: u8,
        serial: &str,
        mode: DepthMode,
        fps: u32,
    ) -> Result<Self, RealSenseError> {
        Self::open_streams(id, serial, mode, fps, true)
    }

    fn open_streams(
        id: u8,
        serial: &str,
        mode: DepthMode,
        fps: u32,
        colour: bool,
    ) -> Result<Self, RealSenseError> {
        let ctx = Context::live()?;
        let found = list(ctx)?;
        if !found.iter().any(|d| d.serial == serial) {
            return Err(RealSenseError::NotConnected {
                serial: serial.to_string(),
                connected: found
                    .iter()
                    .map(|d| format!("{} ({})", d.serial, d.name))
                    .collect(),
            });
        }
        let (w, h) = mode.size();
        let (wi, hi, f) = (w as i32, h as i32, i32::try_from(fps).unwrap_or(i32::MAX));
        let mut streams: Vec<StreamRequest> = vec![
            (ffi::STREAM_DEPTH, 0, wi, hi, ffi::FORMAT_Z16, f),
            (ffi::STREAM_INFRARED, 1, wi, hi, ffi::FORMAT_Y8, f),
        ];
        if colour {
            streams.push((ffi::STREAM_COLOR, 0, wi, hi, ffi::FORMAT_RGB8, f));
        }
        let pipeline =
            Pipeline::start(Source::Device(serial), &streams, |e| RealSenseError::Mode {
                serial: serial.to_string(),
                width: w,
                height: h,
                fps,
                message: e.to_string(),
            })?;
        Self::started(id, serial.to_string(), pipeline)
    }

    /// Plays a librealsense recording (`.bag` or, from 2.59 on, `.db3`) once, as fast as
    /// frames are captured, through the same pipeline as a live device (colour, when
    /// recorded, aligned to depth); past the last frame `capture` times out. One recording plays at a time per process
    /// ([`RealSenseError::PlaybackBusy`] otherwise).
    pub fn open_recording(id: u8, path: &Path) -> Result<Self, RealSenseError> {
        let slot = PlaybackSlot::take(path)?;
        let pipeline = Pipeline::start(Source::File(path), &[], |e| {
            RealSenseError::call(&e, &format!("opening {}", path.display()))
        })?;
        let mut cam = Self::started(id, path.display().to_string(), pipeline)?;
        cam._playback = Some(slot);
        Ok(cam)
    }

    fn started(id: u8, source: String, pipeline: Pipeline) -> Result<Self, RealSenseError> {
        let streams = pipeline
            .streams()
            .map_err(|e| RealSenseError::call(&e, "reading the stream profiles"))?;
        let depth = streams
            .iter()
            .find(|s| s.stream == ffi::STREAM_DEPTH && s.format == ffi::FORMAT_Z16)
            .ok_or_else(|| RealSenseError::BadFrame {
                camera: id,
                what: format!("{source} has no Z16 depth stream"),
            })?;
        let ir = streams
            .iter()
            .filter(|s| s.stream == ffi::STREAM_INFRARED && s.format == ffi::FORMAT_Y8)
            .min_by_key(|s| s.index);
        let colour = streams
            .iter()
            .find(|s| s.stream == ffi::STREAM_COLOR && s.format == ffi::FORMAT_RGB8)
            .map(|s| StreamIntrinsics::from_raw(&s.intrinsics));
        let align = match colour {
            Some(_) => Some(Align::to_depth()?),
            None => None,
        };
        Ok(Self {
            id,
            source,
            align,
            colour,
            depth: StreamIntrinsics::from_raw(&depth.intrinsics),
            ir: ir.map(|s| StreamIntrinsics::from_raw(&s.intrinsics)),
            fps: u32::try_from(depth.fps).unwrap_or(0),
            pipeline,
            timeout_ms: DEFAULT_TIMEOUT_MS,
            _playback: None,
        })
    }

    /// Depth intrinsics as the device reports them.
    pub fn depth_intrinsics(&self) -> &StreamIntrinsics {
        &self.depth
    }

    /// Left IR intrinsics (the same as depth on a D455), when the IR stream runs.
    pub fn ir_intrinsics(&self) -> Option<&StreamIntrinsics> {
        self.ir.as_ref()
    }

    /// Colour intrinsics (before alignment; aligned frames use the depth intrinsics), when
    /// the colour stream runs.
    pub fn colour_intrinsics(&self) -> Option<&StreamIntrinsics> {
        self.colour.as_ref()
    }

    /// The depth stream's frame rate (Hz).
    pub fn fps(&self) -> u32 {
        self.fps
    }

    /// The serial (or recording path) this camera streams from.
    pub fn source(&self) -> &str {
        &self.source
    }

    /// Sets how long `capture` waits for a frameset.
    pub fn set_timeout(&mut self, timeout: Duration) {
        self.timeout_ms = u32::try_from(timeout.as_millis()).unwrap_or(u32::MAX);
    }

    /// The next frameset as a [`CameraFrame`] (depth in millimetres), or a typed error.
    pub fn next_frame(&mut self) -> Result<CameraFrame, RealSenseError> {
        let camera = self.id;
        let set = self
            .pipeline
            .try_wait(self.timeout_ms)
            .map_err(call("waiting for frames"))?
            .ok_or(RealSenseError::Timeout {
                camera,
                timeout_ms: u64::from(self.timeout_ms),
            })?;
        let bad = |what: String| RealSenseError::BadFrame { camera, what };
        let set = match &mut self.align {
            Some(align) => align
                .process(&set)
                .map_err(call("aligning colour to depth"))?
                .ok_or_else(|| bad("the align block returned no frameset".into()))?,
            None => set,
        };
        let mut depth = None;
        let mut colour: Option<Image<Rgb>> = None;
        let mut ir: Option<(i32, Image<u8>)> = None;
        for part in set.parts().map_err(call("splitting the frameset"))? {
            let p = part.profile().map_err(call("reading a frame's profile"))?;
            if p.stream == ffi::STREAM_DEPTH && p.format == ffi::FORMAT_Z16 {
                let units = part.depth_units().map_err(call("reading depth units"))?;
                let ts = part.timestamp_ms().map_err(call("reading the timestamp"))?;
                let px = part.pixels().map_err(call("reading depth pixels"))?;
                depth = Some((to_millimetres(&px, units).map_err(bad)?, ts));
            } else if p.stream == ffi::STREAM_INFRARED
                && p.format == ffi::FORMAT_Y8
                && ir.as_ref().is_none_or(|(index, _)| p.index < *index)
            {
                let px = part.pixels().map_err(call("reading IR pixels"))?;
                let img = Image::new(px.width, px.height, px.bytes)
                    .map_err(|e| bad(format!("IR image: {e}")))?;
                ir = Some((p.index, img));
            } else if p.stream == ffi::STREAM_COLOR && p.format == ffi::FORMAT_RGB8 {
                let px = part.pixels().map_err(call("reading colour pixels"))?;
                let rgb = px
                    .bytes
                    .chunks_exact(3)
                    .map(|c| [c[0], c[1], c[2]])
                    .collect();
                colour = Some(
                    Image::new(px.width, px.height, rgb)
                        .map_err(|e| bad(format!("colour image: {e}")))?,
                );
            }
        }
        let (raw, ts) = depth.ok_or_else(|| bad("the frameset has no Z16 depth frame".into()))?;
        Ok(CameraFrame {
            camera,
            timestamp: Duration::try_from_secs_f64(ts / 1000.0).unwrap_or_default(),
            depth: DepthImage {
                raw,
                depth_scale: DEPTH_SCALE_MM,
            },
            ir: ir.map(|(_, img)| img),
            colour,
        })
    }
}

/// Z16 pixels in `units` metres per count to u16 millimetres (0 stays "no depth"; a value
/// beyond 65.535 m becomes 0 too rather than a wrong distance).
fn to_millimetres(px: &ffi::Pixels, units: f32) -> Result<Image<u16>, String> {
    if px.bytes_per_pixel != 2 {
        return Err(format!(
            "depth has {} bytes per pixel, expected 2",
            px.bytes_per_pixel
        ));
    }
    if !(units.is_finite() && units > 0.0) {
        return Err(format!("depth units {units} m are not positive"));
    }
    let raw = px
        .bytes
        .chunks_exact(2)
        .map(|b| u16::from_ne_bytes([b[0], b[1]]));
    let data: Vec<u16> = if units == DEPTH_SCALE_MM {
        raw.collect()
    } else {
        // Units are decimal settings (100 um, 1 mm) stored as f32: take the shortest decimal
        // that round-trips, so 0.0001f32 counts as 0.0001 rather than 0.000099999997.
        let units_m = units.to_string().parse::<f64>().unwrap_or(f64::from(units));
        let per_count = units_m * 1000.0;
        raw.map(|r| {
            let mm = (f64::from(r) * per_count).round();
            if mm <= f64::from(u16::MAX) {
                mm as u16
            } else {
                0
            }
        })
        .collect()
    };
    Image::new(px.width, px.height, data).map_err(|e| format!("depth image: {e}"))
}

impl DepthCamera for RealSenseCamera {
    fn id(&self) -> u8 {
        self.id
    }

    fn capture(&mut self) -> Result<CameraFrame, CameraError> {
        let camera = self.id;
        self.next_frame().map_err(|e| camera_error(camera, e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pixels(values: &[u16]) -> ffi::Pixels {
        ffi::Pixels {
            width: values.len() as u32,
            height: 1,
            bytes_per_pixel: 2,
            bytes: values.iter().flat_map(|v| v.to_ne_bytes()).collect(),
        }
    }

    #[test]
    fn millimetre_units_are_copied_and_others_converted() {
        let px = pixels(&[0, 1, 1234, u16::MAX]);
        assert_eq!(
            to_millimetres(&px, 0.001).unwrap().data,
            vec![0, 1, 1234, u16::MAX]
        );
        // 100 um units: 12346 counts are 1234.6 mm, rounded.
        let px = pixels(&[0, 12346, 12344, 10]);
        assert_eq!(
            to_millimetres(&px, 0.0001).unwrap().data,
            vec![0, 1235, 1234, 1]
        );
        // 2 mm units: 40000 counts are 80 m, which u16 millimetres cannot hold: no depth.
        let px = pixels(&[40000, 100]);
        assert_eq!(to_millimetres(&px, 0.002).unwrap().data, vec![0, 200]);
        assert!(to_millimetres(&px, 0.0).is_err());
    }

    #[test]
    fn not_connected_lists_what_was_found() {
        let e = RealSenseError::NotConnected {
            serial: "123".into(),
            connected: vec![],
        };
        assert!(e
            .to_string()
            .starts_with("no D455 with serial 123; connected: none;"));
        let e = RealSenseError::NotConnected {
            serial: "123".into(),
            connected: vec!["9 (D455)".into(), "8 (D435)".into()],
        };
        assert!(e.to_string().contains("connected: 9 (D455), 8 (D435);"));
    }

    #[test]
    fn timeouts_stay_timeouts_for_the_trait() {
        let e = camera_error(
            2,
            RealSenseError::Timeout {
                camera: 2,
                timeout_ms: 40,
            },
        );
        assert_eq!(
            e,
            CameraError::Timeout {
                camera: 2,
                timeout_ms: 40
            }
        );
        let e = camera_error(
            2,
            RealSenseError::Call {
                doing: "waiting for frames".into(),
                function: "rs2_pipeline_try_wait_for_frames".into(),
                message: "USB transfer failed".into(),
            },
        );
        assert!(
            matches!(&e, CameraError::Device { camera: 2, message } if message.contains("USB transfer failed")),
            "{e:?}"
        );
    }
}
