//! Captures and the captures folder (issue 8 items 1 and 2).
//!
//! A *capture* is one robot pose: the joint state (when known), the flange pose the robot
//! reported for it (`base_from_flange`, from the controller or from FK of the joints), and
//! for every camera that saw the board the detected corner pixels (and, optionally, depth
//! samples on the board for the depth residual).
//!
//! Folder layout (plain JSON, readable by any tool, e.g. the OpenCV peer in `tests/peers`):
//! - `session.json`: [`Session`]: format tag, board layout, pixel convention, cameras with
//!   their intrinsics.
//! - `pose_0000.json`, `pose_0001.json`, ...: one [`Capture`] per robot pose.
//! - `truth.json` (simulated captures only): the ground truth, ignored by the loader.
//!
//! Every file is written atomically (write `*.tmp`, fsync, rename), so an interrupted
//! capture leaves only whole files behind; [`CaptureFolder::missing`] tells a resumed
//! capture which poses still need doing, and nothing ever overwrites a captured pose.
//!
//! Pixel convention: a session states its [`PixelConvention`]; [`load_captures`] converts
//! all pixels to the crate's convention (librealsense: pixel (0, 0) is the *centre* of the
//! top-left pixel), so detectors that put the centre at (0.5, 0.5) (AprilTag's C detector,
//! Open3D ray casting) cannot cause a fake half-pixel error.
//!
//! Poses are JSON as nalgebra writes an `Isometry3`:
//! `{"rotation": [qx, qy, qz, qw], "translation": [x, y, z]}` (metres).

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use cell_types::{Base, Flange, Joints, Transform};
use serde::{Deserialize, Serialize};

use crate::board::BoardConfig;
use crate::camera::Intrinsics;
use crate::error::CalibrationError;

/// The format tag in `session.json`.
pub const CAPTURES_FORMAT: &str = "equact-calibration-captures/1";
/// The session file's name.
pub const SESSION_FILE: &str = "session.json";

/// Where integer pixel coordinates lie on a pixel.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum PixelConvention {
    /// (0, 0) is the centre of the top-left pixel (librealsense, OpenCV; this crate's own).
    #[default]
    CentreAtInteger,
    /// (0.5, 0.5) is the centre of the top-left pixel (AprilTag C detector, Open3D).
    CornerAtInteger,
}

impl PixelConvention {
    /// Converts a pixel in this convention to [`PixelConvention::CentreAtInteger`].
    pub fn to_centre_at_integer(self, u: f64, v: f64) -> (f64, f64) {
        match self {
            PixelConvention::CentreAtInteger => (u, v),
            PixelConvention::CornerAtInteger => (u - 0.5, v - 0.5),
        }
    }
}

/// One camera of a capture session.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    /// Camera id (`FrameId::Camera` index).
    pub id: u8,
    /// Name (e.g. `front`).
    pub name: String,
    /// Intrinsics of the stream the corners were detected in (left IR = depth intrinsics).
    pub intrinsics: Intrinsics,
}

/// What every capture of a folder shares (`session.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Session {
    /// Format tag, [`CAPTURES_FORMAT`].
    pub format: String,
    /// The board on the flange.
    pub board: BoardConfig,
    /// The pixel convention of the corner and depth pixels in the pose files.
    pub pixel_convention: PixelConvention,
    /// The cameras.
    pub cameras: Vec<CameraInfo>,
}

impl Session {
    /// A session in this crate's pixel convention.
    pub fn new(board: BoardConfig, cameras: Vec<CameraInfo>) -> Self {
        Self {
            format: CAPTURES_FORMAT.to_string(),
            board,
            pixel_convention: PixelConvention::CentreAtInteger,
            cameras,
        }
    }

    /// The camera with id `id`.
    pub fn camera(&self, id: u8) -> Option<&CameraInfo> {
        self.cameras.iter().find(|c| c.id == id)
    }
}

/// One detected board corner.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Corner {
    /// Corner id (see [`BoardConfig::corner`]).
    pub id: u32,
    /// Column (px).
    pub u: f64,
    /// Row (px).
    pub v: f64,
}

/// A depth measured at a pixel on the board.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DepthSample {
    /// Column (px).
    pub u: f64,
    /// Row (px).
    pub v: f64,
    /// Depth (m, the z coordinate).
    pub depth_m: f64,
}

/// What one camera saw at one robot pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraView {
    /// Camera id.
    pub camera: u8,
    /// Detected corners (sub-pixel).
    pub corners: Vec<Corner>,
    /// Depth samples on the board (optional).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub board_depth: Vec<DepthSample>,
}

/// One robot pose and what the cameras saw there (`pose_NNNN.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Capture {
    /// Pose index (the file's number).
    pub index: usize,
    /// The joint state (rad), when the robot reported it.
    #[serde(default)]
    pub joints: Option<Joints>,
    /// The flange pose the robot reported (FK of `joints`).
    pub base_from_flange: Transform<Base, Flange>,
    /// One entry per camera that saw the board.
    pub views: Vec<CameraView>,
}

impl Capture {
    /// The view of camera `id`, if it saw the board.
    pub fn view(&self, id: u8) -> Option<&CameraView> {
        self.views.iter().find(|v| v.camera == id)
    }
}

/// A loaded captures folder: the session and its captures in index order, all pixels in
/// [`PixelConvention::CentreAtInteger`].
#[derive(Clone, Debug, PartialEq)]
pub struct CaptureSet {
    /// The session.
    pub session: Session,
    /// The captures, by increasing index.
    pub captures: Vec<Capture>,
}

impl CaptureSet {
    /// Checks the captures against the session (camera ids, corner ids, finite numbers,
    /// unique indices); `origin` names the folder in errors.
    pub fn validate(&self, origin: &str) -> Result<(), CalibrationError> {
        self.session.board.validate()?;
        validate_session(&self.session, origin)?;
        let mut seen = BTreeSet::new();
        for c in &self.captures {
            let file = format!("{origin}/{}", pose_file_name(c.index));
            if !seen.insert(c.index) {
                return Err(inconsistent(
                    &file,
                    format!("pose index {} appears twice", c.index),
                    "keep one of the two files",
                ));
            }
            validate_capture(&self.session, c, &file)?;
        }
        Ok(())
    }

    /// Checks every capture's joint state against its flange pose with the robot's forward
    /// kinematics `fk`; a capture whose FK differs by more than `tol_m` / `tol_rad` has a
    /// joint file from another moment (or another robot): it is named in the error.
    pub fn check_joints(
        &self,
        fk: impl Fn(&Joints) -> Transform<Base, Flange>,
        tol_m: f64,
        tol_rad: f64,
    ) -> Result<(), CalibrationError> {
        for c in &self.captures {
            let Some(q) = c.joints else { continue };
            let (dt, dr) = fk(&q).error_to(&c.base_from_flange);
            if !(dt <= tol_m && dr <= tol_rad) {
                return Err(inconsistent(
                    &pose_file_name(c.index),
                    format!(
                        "FK of its joint state is {:.2} mm / {:.3} deg from its flange pose",
                        dt * 1e3,
                        dr.to_degrees()
                    ),
                    &format!(
                        "joints and flange pose were not recorded together: delete {} and re-capture pose {} (the other poses are kept)",
                        pose_file_name(c.index),
                        c.index
                    ),
                ));
            }
        }
        Ok(())
    }
}

fn inconsistent(path: &str, why: String, what_to_do: &str) -> CalibrationError {
    CalibrationError::InconsistentCaptures {
        path: path.to_string(),
        why,
        what_to_do: what_to_do.to_string(),
    }
}

fn io_err(path: &Path, e: impl std::fmt::Display) -> CalibrationError {
    CalibrationError::CaptureIo {
        path: path.display().to_string(),
        why: e.to_string(),
    }
}

fn validate_session(s: &Session, origin: &str) -> Result<(), CalibrationError> {
    let file = format!("{origin}/{SESSION_FILE}");
    if s.format != CAPTURES_FORMAT {
        return Err(inconsistent(
            &file,
            format!("format {:?}, expected {CAPTURES_FORMAT:?}", s.format),
            "capture again with this version, or convert the folder",
        ));
    }
    if s.cameras.is_empty() {
        return Err(inconsistent(
            &file,
            "no cameras listed".into(),
            "list the cameras (id, name, intrinsics)",
        ));
    }
    for (i, c) in s.cameras.iter().enumerate() {
        if s.cameras[..i].iter().any(|o| o.id == c.id) {
            return Err(CalibrationError::DuplicateCamera { camera: c.id });
        }
        c.intrinsics.validate()?;
    }
    Ok(())
}

fn validate_capture(s: &Session, c: &Capture, file: &str) -> Result<(), CalibrationError> {
    let redo = format!(
        "delete {} and re-capture pose {} (the other poses are kept)",
        pose_file_name(c.index),
        c.index
    );
    if !c.base_from_flange.is_finite() {
        return Err(inconsistent(
            file,
            "base_from_flange is not a finite rigid transform".into(),
            &redo,
        ));
    }
    if let Some(q) = c.joints {
        if q.iter().any(|a| !a.is_finite()) {
            return Err(inconsistent(
                file,
                "a joint angle is not finite".into(),
                &redo,
            ));
        }
    }
    for (i, v) in c.views.iter().enumerate() {
        if s.camera(v.camera).is_none() {
            return Err(inconsistent(
                file,
                format!(
                    "camera {} is not in the session (cameras {:?})",
                    v.camera,
                    s.cameras.iter().map(|c| c.id).collect::<Vec<_>>()
                ),
                &redo,
            ));
        }
        if c.views[..i].iter().any(|o| o.camera == v.camera) {
            return Err(inconsistent(
                file,
                format!("camera {} has two views", v.camera),
                &redo,
            ));
        }
        let mut ids = BTreeSet::new();
        for k in &v.corners {
            if k.id as usize >= s.board.corner_count() || !ids.insert(k.id) {
                return Err(inconsistent(
                    file,
                    format!(
                        "camera {}: corner id {} is out of range or repeated (the board has {} corners)",
                        v.camera,
                        k.id,
                        s.board.corner_count()
                    ),
                    &format!("check the board layout in {SESSION_FILE}, or {redo}"),
                ));
            }
            if !(k.u.is_finite() && k.v.is_finite()) {
                return Err(inconsistent(
                    file,
                    format!("camera {}: corner {} is not finite", v.camera, k.id),
                    &redo,
                ));
            }
        }
        if let Some(d) = v.board_depth.iter().find(|d| {
            !(d.u.is_finite() && d.v.is_finite() && d.depth_m.is_finite() && d.depth_m > 0.0)
        }) {
            return Err(inconsistent(
                file,
                format!(
                    "camera {}: depth sample {d:?} is not a positive finite depth",
                    v.camera
                ),
                &redo,
            ));
        }
    }
    Ok(())
}

/// The file name of pose `index`.
pub fn pose_file_name(index: usize) -> String {
    format!("pose_{index:04}.json")
}

/// The pose index of a file name `pose_NNNN.json`, or `None` for other files.
fn pose_index(name: &str) -> Option<usize> {
    name.strip_prefix("pose_")?
        .strip_suffix(".json")?
        .parse()
        .ok()
}

/// Writes `bytes` to `path` atomically: a sibling `*.tmp` file, fsync, rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), CalibrationError> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    let mut f = fs::File::create(&tmp).map_err(|e| io_err(&tmp, e))?;
    f.write_all(bytes).map_err(|e| io_err(&tmp, e))?;
    f.sync_all().map_err(|e| io_err(&tmp, e))?;
    drop(f);
    fs::rename(&tmp, path).map_err(|e| io_err(path, e))?;
    // Make the rename itself durable where the platform allows opening a folder.
    if let Some(dir) = path.parent() {
        if let Ok(d) = fs::File::open(dir) {
            let _ = d.sync_all();
        }
    }
    Ok(())
}

fn to_json<T: Serialize>(value: &T, path: &Path) -> Result<Vec<u8>, CalibrationError> {
    let mut v = serde_json::to_vec_pretty(value).map_err(|e| io_err(path, e))?;
    v.push(b'\n');
    Ok(v)
}

fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, CalibrationError> {
    let text = fs::read_to_string(path).map_err(|e| io_err(path, e))?;
    serde_json::from_str(&text).map_err(|e| {
        inconsistent(
            &path.display().to_string(),
            format!("not valid JSON for this file: {e}"),
            "delete this file and capture that pose again (the other poses are kept)",
        )
    })
}

/// A captures folder open for writing; resumes where an earlier capture stopped.
#[derive(Debug)]
pub struct CaptureFolder {
    dir: PathBuf,
    session: Session,
    existing: BTreeSet<usize>,
}

impl CaptureFolder {
    /// Opens `dir` for capturing with `session`: creates it (and `session.json`) when new;
    /// when it already holds a session, that session must equal `session` (same board,
    /// pixel convention and cameras), and its poses are kept.
    pub fn create_or_resume(dir: &Path, session: &Session) -> Result<Self, CalibrationError> {
        session.board.validate()?;
        validate_session(session, &dir.display().to_string())?;
        fs::create_dir_all(dir).map_err(|e| io_err(dir, e))?;
        let path = dir.join(SESSION_FILE);
        if path.exists() {
            let old: Session = read_json(&path)?;
            if &old != session {
                return Err(inconsistent(
                    &path.display().to_string(),
                    "the folder was captured with another board, pixel convention or camera set"
                        .into(),
                    "capture into a new folder, or resume with the same configuration",
                ));
            }
        } else {
            write_atomic(&path, &to_json(session, &path)?)?;
        }
        let existing = list_pose_files(dir)?.into_keys().collect();
        Ok(Self {
            dir: dir.to_path_buf(),
            session: session.clone(),
            existing,
        })
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The session.
    pub fn session(&self) -> &Session {
        &self.session
    }

    /// Indices of the poses already captured.
    pub fn existing(&self) -> &BTreeSet<usize> {
        &self.existing
    }

    /// The indices in `0..planned` not captured yet (what a resumed capture still does).
    pub fn missing(&self, planned: usize) -> Vec<usize> {
        (0..planned)
            .filter(|i| !self.existing.contains(i))
            .collect()
    }

    /// Writes one capture atomically. A pose already captured is never overwritten: delete
    /// its file first to capture it again.
    pub fn write(&mut self, capture: &Capture) -> Result<PathBuf, CalibrationError> {
        let path = self.dir.join(pose_file_name(capture.index));
        validate_capture(&self.session, capture, &path.display().to_string())?;
        if self.existing.contains(&capture.index) || path.exists() {
            return Err(inconsistent(
                &path.display().to_string(),
                format!("pose {} is already captured", capture.index),
                "delete the file to capture that pose again; nothing was overwritten",
            ));
        }
        write_atomic(&path, &to_json(capture, &path)?)?;
        self.existing.insert(capture.index);
        Ok(path)
    }
}

/// Pose files of `dir` by index (`*.tmp` leftovers of an interrupted write are ignored).
fn list_pose_files(dir: &Path) -> Result<BTreeMap<usize, PathBuf>, CalibrationError> {
    let mut out = BTreeMap::new();
    for entry in fs::read_dir(dir).map_err(|e| io_err(dir, e))? {
        let entry = entry.map_err(|e| io_err(dir, e))?;
        let name = entry.file_name();
        let Some(index) = name.to_str().and_then(pose_index) else {
            continue;
        };
        if let Some(other) = out.insert(index, entry.path()) {
            return Err(inconsistent(
                &entry.path().display().to_string(),
                format!("pose index {index} also in {}", other.display()),
                "keep one of the two files",
            ));
        }
    }
    Ok(out)
}

/// Loads a captures folder: the session, every `pose_NNNN.json` (checked against the
/// session), pixels converted to [`PixelConvention::CentreAtInteger`].
pub fn load_captures(dir: &Path) -> Result<CaptureSet, CalibrationError> {
    let session_path = dir.join(SESSION_FILE);
    if !session_path.exists() {
        return Err(inconsistent(
            &dir.display().to_string(),
            format!("no {SESSION_FILE}: this is not a captures folder"),
            "run `equact calibrate capture` (or `simulate`) into it first",
        ));
    }
    let mut session: Session = read_json(&session_path)?;
    session.board.validate()?;
    validate_session(&session, &dir.display().to_string())?;
    let mut captures = Vec::new();
    for (index, path) in list_pose_files(dir)? {
        let c: Capture = read_json(&path)?;
        if c.index != index {
            return Err(inconsistent(
                &path.display().to_string(),
                format!("the file says index {} but its name says {index}", c.index),
                "rename the file to match its index, or delete it and re-capture that pose",
            ));
        }
        captures.push(c);
    }
    let conv = session.pixel_convention;
    for c in &mut captures {
        for v in &mut c.views {
            for k in &mut v.corners {
                (k.u, k.v) = conv.to_centre_at_integer(k.u, k.v);
            }
            for d in &mut v.board_depth {
                (d.u, d.v) = conv.to_centre_at_integer(d.u, d.v);
            }
        }
    }
    session.pixel_convention = PixelConvention::CentreAtInteger;
    let set = CaptureSet { session, captures };
    set.validate(&dir.display().to_string())?;
    Ok(set)
}

/// Writes a whole capture set into a new or resumable folder (poses already there are
/// kept, not overwritten); returns the folder.
pub fn write_captures(dir: &Path, set: &CaptureSet) -> Result<CaptureFolder, CalibrationError> {
    let mut folder = CaptureFolder::create_or_resume(dir, &set.session)?;
    for c in &set.captures {
        if !folder.existing().contains(&c.index) {
            folder.write(c)?;
        }
    }
    Ok(folder)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::DepthMode;

    fn tmp_dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("calib-capture-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&d);
        d
    }

    fn session() -> Session {
        Session::new(
            BoardConfig::default(),
            vec![CameraInfo {
                id: 0,
                name: "front".into(),
                intrinsics: Intrinsics::d455_depth(DepthMode::Wvga848x480),
            }],
        )
    }

    fn capture(index: usize) -> Capture {
        Capture {
            index,
            joints: Some([0.1, -1.2, 1.3, -1.6, -1.57, 0.2]),
            base_from_flange: Transform::from_xyz_rpy([0.5, 0.1, 0.4], [3.0, 0.1, 0.2]),
            views: vec![CameraView {
                camera: 0,
                corners: vec![
                    Corner {
                        id: 0,
                        u: 100.25,
                        v: 200.5,
                    },
                    Corner {
                        id: 1,
                        u: 110.0,
                        v: 200.0,
                    },
                ],
                board_depth: vec![DepthSample {
                    u: 105.0,
                    v: 201.0,
                    depth_m: 1.002,
                }],
            }],
        }
    }

    #[test]
    fn folder_round_trips_resumes_and_never_overwrites() {
        let dir = tmp_dir("roundtrip");
        let mut f = CaptureFolder::create_or_resume(&dir, &session()).unwrap();
        assert!(f.existing().is_empty());
        f.write(&capture(0)).unwrap();
        f.write(&capture(2)).unwrap();
        // An interrupted write leaves a .tmp file: ignored, and pose 1 is still missing.
        fs::write(dir.join("pose_0001.json.tmp"), b"{\"index\": 1, \"jo").unwrap();
        let mut resumed = CaptureFolder::create_or_resume(&dir, &session()).unwrap();
        assert_eq!(resumed.missing(4), vec![1, 3]);
        let err = resumed.write(&capture(2)).unwrap_err();
        assert!(
            matches!(err, CalibrationError::InconsistentCaptures { .. }),
            "{err}"
        );
        resumed.write(&capture(1)).unwrap();
        let set = load_captures(&dir).unwrap();
        assert_eq!(set.captures.len(), 3);
        assert_eq!(set.captures[1], capture(1));
        assert_eq!(set.session, session());
        // The pose JSON is nalgebra's isometry layout, for other tools.
        let text = fs::read_to_string(dir.join("pose_0000.json")).unwrap();
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(v["base_from_flange"]["translation"][0].as_f64(), Some(0.5));
        assert_eq!(
            v["base_from_flange"]["rotation"].as_array().unwrap().len(),
            4
        );
        // Resuming with another board is refused, and nothing is lost.
        let mut other = session();
        other.board.square_m = 0.04;
        assert!(matches!(
            CaptureFolder::create_or_resume(&dir, &other),
            Err(CalibrationError::InconsistentCaptures { .. })
        ));
        assert_eq!(load_captures(&dir).unwrap().captures.len(), 3);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn corner_at_integer_pixels_are_shifted_by_half_a_pixel() {
        let dir = tmp_dir("convention");
        let mut s = session();
        s.pixel_convention = PixelConvention::CornerAtInteger;
        let mut f = CaptureFolder::create_or_resume(&dir, &s).unwrap();
        f.write(&capture(0)).unwrap();
        let set = load_captures(&dir).unwrap();
        assert_eq!(
            set.session.pixel_convention,
            PixelConvention::CentreAtInteger
        );
        let k = set.captures[0].views[0].corners[0];
        assert_eq!((k.u, k.v), (99.75, 200.0));
        assert_eq!(set.captures[0].views[0].board_depth[0].u, 104.5);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn broken_files_are_named_with_what_to_do() {
        let dir = tmp_dir("broken");
        let mut f = CaptureFolder::create_or_resume(&dir, &session()).unwrap();
        f.write(&capture(0)).unwrap();
        fs::write(dir.join("pose_0001.json"), b"{ not json").unwrap();
        let err = load_captures(&dir).unwrap_err();
        let msg = err.to_string();
        assert!(
            msg.contains("pose_0001.json") && msg.contains("re-capture")
                || msg.contains("capture that pose again"),
            "{msg}"
        );
        fs::remove_file(dir.join("pose_0001.json")).unwrap();
        // A corner id past the board, and an unknown camera.
        let mut bad = capture(1);
        bad.views[0].corners[0].id = 10_000;
        fs::write(
            dir.join("pose_0001.json"),
            serde_json::to_vec(&bad).unwrap(),
        )
        .unwrap();
        assert!(matches!(
            load_captures(&dir),
            Err(CalibrationError::InconsistentCaptures { .. })
        ));
        let mut bad = capture(1);
        bad.views[0].camera = 7;
        fs::write(
            dir.join("pose_0001.json"),
            serde_json::to_vec(&bad).unwrap(),
        )
        .unwrap();
        let msg = load_captures(&dir).unwrap_err().to_string();
        assert!(msg.contains("camera 7"), "{msg}");
        // A file whose index disagrees with its name.
        fs::write(
            dir.join("pose_0001.json"),
            serde_json::to_vec(&capture(5)).unwrap(),
        )
        .unwrap();
        assert!(load_captures(&dir)
            .unwrap_err()
            .to_string()
            .contains("index 5"));
        // Not a captures folder at all.
        let empty = tmp_dir("empty");
        fs::create_dir_all(&empty).unwrap();
        assert!(load_captures(&empty)
            .unwrap_err()
            .to_string()
            .contains("session.json"));
        fs::remove_dir_all(&dir).unwrap();
        fs::remove_dir_all(&empty).unwrap();
    }

    #[test]
    fn joint_states_that_disagree_with_the_flange_pose_are_named() {
        let set = CaptureSet {
            session: session(),
            captures: vec![capture(0), capture(1)],
        };
        let good = capture(0).base_from_flange;
        set.check_joints(|_| good, 1e-4, 1e-4).unwrap();
        let off = Transform::from_xyz_rpy([0.51, 0.1, 0.4], [3.0, 0.1, 0.2]);
        let err = set.check_joints(|_| off, 1e-4, 1e-4).unwrap_err();
        let msg = err.to_string();
        assert!(
            msg.contains("pose_0000.json") && msg.contains("10.00 mm"),
            "{msg}"
        );
    }
}
