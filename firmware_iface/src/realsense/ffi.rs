//! The few librealsense2 C API functions the D455 driver uses, loaded at run time with
//! `libloading` (dlopen), and thin owning wrappers around its handles. This is the only
//! module of the crate with `unsafe` code.
//!
//! Declarations follow librealsense's `rs.h`, `rs_types.h`, `rs_context.h`, `rs_device.h`,
//! `rs_pipeline.h`, `rs_config.h`, `rs_frame.h`, `rs_processing.h` and
//! `rs_record_playback.h` (API 2.x; the context asks for 2.50 or newer, and the tests run
//! 2.59). Every call but the deleters and releases takes a trailing `rs2_error**`: a
//! non-null error after the call means it failed, and its message is carried into
//! [`Rs2Error`]. A function missing from the loaded library is a typed error at load time.
//!
//! The library is loaded once per process and never unloaded: librealsense starts its own
//! threads (device watcher, USB transfer and frame dispatch threads per streaming sensor),
//! and unloading code those threads run would be unsound.

#![allow(unsafe_code)]

use std::ffi::{c_char, c_double, c_float, c_int, c_uint, c_void, CStr, CString};
use std::path::{Path, PathBuf};
use std::ptr;
use std::sync::{Mutex, OnceLock};

use libloading::Library;

use super::RealSenseError;

/// The oldest API version this module is written against (2.50.0, as `rs2_create_context`
/// encodes it: major * 10000 + minor * 100 + patch); the library refuses older ones.
const API_VERSION: c_int = 25000;

/// `rs2_stream`: depth.
pub const STREAM_DEPTH: c_int = 1;
/// `rs2_stream`: colour.
pub const STREAM_COLOR: c_int = 2;
/// `rs2_stream`: infrared.
pub const STREAM_INFRARED: c_int = 3;
/// `rs2_format`: 16-bit depth.
pub const FORMAT_Z16: c_int = 1;
/// `rs2_format`: 8-bit RGB.
pub const FORMAT_RGB8: c_int = 5;
/// `rs2_format`: 8-bit luminance.
pub const FORMAT_Y8: c_int = 9;
/// `rs2_camera_info`: device name.
const INFO_NAME: c_int = 0;
/// `rs2_camera_info`: serial number.
const INFO_SERIAL_NUMBER: c_int = 1;

macro_rules! opaque {
    ($($name:ident),*) => {$(
        /// An opaque librealsense handle type.
        #[repr(C)]
        pub struct $name {
            _private: [u8; 0],
        }
    )*};
}
opaque!(
    RsError,
    RsContext,
    RsDeviceList,
    RsDevice,
    RsConfig,
    RsPipeline,
    RsPipelineProfile,
    RsStreamProfileList,
    RsStreamProfile,
    RsFrame,
    RsProcessingBlock,
    RsFrameQueue
);

/// `rs2_intrinsics`.
#[repr(C)]
#[derive(Copy, Clone, Debug, Default)]
pub struct RsIntrinsics {
    /// Width (px).
    pub width: c_int,
    /// Height (px).
    pub height: c_int,
    /// Principal point x (px).
    pub ppx: c_float,
    /// Principal point y (px).
    pub ppy: c_float,
    /// Focal length x (px).
    pub fx: c_float,
    /// Focal length y (px).
    pub fy: c_float,
    /// `rs2_distortion`.
    pub model: c_int,
    /// Distortion coefficients.
    pub coeffs: [c_float; 5],
}

type Err = *mut *mut RsError;

/// The function table: one pointer per C function used, valid while `_lib` is loaded
/// (forever: the table lives in a static).
struct Api {
    get_api_version: unsafe extern "C" fn(Err) -> c_int,
    get_error_message: unsafe extern "C" fn(*const RsError) -> *const c_char,
    get_failed_function: unsafe extern "C" fn(*const RsError) -> *const c_char,
    free_error: unsafe extern "C" fn(*mut RsError),
    create_context: unsafe extern "C" fn(c_int, Err) -> *mut RsContext,
    delete_context: unsafe extern "C" fn(*mut RsContext),
    query_devices: unsafe extern "C" fn(*const RsContext, Err) -> *mut RsDeviceList,
    get_device_count: unsafe extern "C" fn(*const RsDeviceList, Err) -> c_int,
    delete_device_list: unsafe extern "C" fn(*mut RsDeviceList),
    create_device: unsafe extern "C" fn(*const RsDeviceList, c_int, Err) -> *mut RsDevice,
    delete_device: unsafe extern "C" fn(*mut RsDevice),
    supports_device_info: unsafe extern "C" fn(*const RsDevice, c_int, Err) -> c_int,
    get_device_info: unsafe extern "C" fn(*const RsDevice, c_int, Err) -> *const c_char,
    create_config: unsafe extern "C" fn(Err) -> *mut RsConfig,
    delete_config: unsafe extern "C" fn(*mut RsConfig),
    config_enable_stream:
        unsafe extern "C" fn(*mut RsConfig, c_int, c_int, c_int, c_int, c_int, c_int, Err),
    config_enable_device: unsafe extern "C" fn(*mut RsConfig, *const c_char, Err),
    config_enable_device_from_file_repeat_option:
        unsafe extern "C" fn(*mut RsConfig, *const c_char, c_int, Err),
    config_resolve:
        unsafe extern "C" fn(*mut RsConfig, *mut RsPipeline, Err) -> *mut RsPipelineProfile,
    create_pipeline: unsafe extern "C" fn(*mut RsContext, Err) -> *mut RsPipeline,
    delete_pipeline: unsafe extern "C" fn(*mut RsPipeline),
    pipeline_start_with_config:
        unsafe extern "C" fn(*mut RsPipeline, *mut RsConfig, Err) -> *mut RsPipelineProfile,
    pipeline_stop: unsafe extern "C" fn(*mut RsPipeline, Err),
    pipeline_try_wait_for_frames:
        unsafe extern "C" fn(*mut RsPipeline, *mut *mut RsFrame, c_uint, Err) -> c_int,
    pipeline_profile_get_device: unsafe extern "C" fn(*mut RsPipelineProfile, Err) -> *mut RsDevice,
    pipeline_profile_get_streams:
        unsafe extern "C" fn(*mut RsPipelineProfile, Err) -> *mut RsStreamProfileList,
    delete_pipeline_profile: unsafe extern "C" fn(*mut RsPipelineProfile),
    get_stream_profiles_count: unsafe extern "C" fn(*const RsStreamProfileList, Err) -> c_int,
    get_stream_profile:
        unsafe extern "C" fn(*const RsStreamProfileList, c_int, Err) -> *const RsStreamProfile,
    delete_stream_profiles_list: unsafe extern "C" fn(*mut RsStreamProfileList),
    get_stream_profile_data: unsafe extern "C" fn(
        *const RsStreamProfile,
        *mut c_int,
        *mut c_int,
        *mut c_int,
        *mut c_int,
        *mut c_int,
        Err,
    ),
    get_video_stream_intrinsics:
        unsafe extern "C" fn(*const RsStreamProfile, *mut RsIntrinsics, Err),
    playback_device_set_real_time: unsafe extern "C" fn(*const RsDevice, c_int, Err),
    playback_device_pause: unsafe extern "C" fn(*const RsDevice, Err),
    embedded_frames_count: unsafe extern "C" fn(*mut RsFrame, Err) -> c_int,
    extract_frame: unsafe extern "C" fn(*mut RsFrame, c_int, Err) -> *mut RsFrame,
    release_frame: unsafe extern "C" fn(*mut RsFrame),
    get_frame_stream_profile: unsafe extern "C" fn(*const RsFrame, Err) -> *const RsStreamProfile,
    get_frame_data: unsafe extern "C" fn(*const RsFrame, Err) -> *const c_void,
    get_frame_width: unsafe extern "C" fn(*const RsFrame, Err) -> c_int,
    get_frame_height: unsafe extern "C" fn(*const RsFrame, Err) -> c_int,
    get_frame_stride_in_bytes: unsafe extern "C" fn(*const RsFrame, Err) -> c_int,
    get_frame_bits_per_pixel: unsafe extern "C" fn(*const RsFrame, Err) -> c_int,
    get_frame_timestamp: unsafe extern "C" fn(*const RsFrame, Err) -> c_double,
    depth_frame_get_units: unsafe extern "C" fn(*const RsFrame, Err) -> c_float,
    frame_add_ref: unsafe extern "C" fn(*mut RsFrame, Err),
    create_align: unsafe extern "C" fn(c_int, Err) -> *mut RsProcessingBlock,
    delete_processing_block: unsafe extern "C" fn(*mut RsProcessingBlock),
    create_frame_queue: unsafe extern "C" fn(c_int, Err) -> *mut RsFrameQueue,
    delete_frame_queue: unsafe extern "C" fn(*mut RsFrameQueue),
    start_processing_queue: unsafe extern "C" fn(*mut RsProcessingBlock, *mut RsFrameQueue, Err),
    process_frame: unsafe extern "C" fn(*mut RsProcessingBlock, *mut RsFrame, Err),
    poll_for_frame: unsafe extern "C" fn(*mut RsFrameQueue, *mut *mut RsFrame, Err) -> c_int,
    /// Keeps the code behind the pointers mapped.
    _lib: Library,
}

/// A failed librealsense call: the function that failed and its message.
#[derive(Clone, Debug, PartialEq)]
pub struct Rs2Error {
    /// The C function that failed (librealsense's name for it).
    pub function: String,
    /// librealsense's message.
    pub message: String,
}

impl std::fmt::Display for Rs2Error {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.function, self.message)
    }
}

/// Copies a C string librealsense owns (null: empty).
fn c_text(p: *const c_char) -> String {
    if p.is_null() {
        return String::new();
    }
    // SAFETY: librealsense returns NUL-terminated strings that live at least as long as the
    // object they came from, which the caller still holds; we copy before returning.
    unsafe { CStr::from_ptr(p) }.to_string_lossy().into_owned()
}

impl Api {
    /// Turns the error out-parameter of a call into a result, freeing the error.
    fn check(&self, err: *mut RsError, function: &str) -> Result<(), Rs2Error> {
        if err.is_null() {
            return Ok(());
        }
        // SAFETY: `err` is a live rs2_error that librealsense just handed us; we read its
        // two strings before freeing it exactly once.
        let (failed, message) = unsafe {
            (
                c_text((self.get_failed_function)(err)),
                c_text((self.get_error_message)(err)),
            )
        };
        // SAFETY: as above; nothing reads `err` after this.
        unsafe { (self.free_error)(err) };
        Err(Rs2Error {
            function: if failed.is_empty() {
                function.to_string()
            } else {
                failed
            },
            message,
        })
    }
}

/// Calls one C function of the table with a trailing error out-parameter and checks it.
macro_rules! call {
    ($api:expr, $f:ident ( $($arg:expr),* )) => {{
        let api: &Api = $api;
        let mut err: *mut RsError = ptr::null_mut();
        // SAFETY: every pointer argument is a live handle owned by one of the wrappers
        // below (or a local out-parameter), matching the C declaration of the function.
        let r = unsafe { (api.$f)($($arg,)* &mut err) };
        api.check(err, concat!("rs2_", stringify!($f))).map(|()| r)
    }};
}

/// Where the library was loaded from, and the table.
static API: OnceLock<(PathBuf, Api)> = OnceLock::new();
/// Serialises the first load and context creation.
static LOADING: Mutex<()> = Mutex::new(());
/// Serialises pipeline starts and stops: two playback pipelines starting or stopping at
/// once in different threads crashed librealsense 2.59 ("pure virtual method called").
static LIFECYCLE: Mutex<()> = Mutex::new(());

/// The environment variable naming librealsense2's shared library.
pub const LIBRARY_ENV: &str = "EQUACT_LIBREALSENSE";

fn load_from(path: &Path) -> Result<Api, RealSenseError> {
    // SAFETY: loading runs the library's initialisers; librealsense2's (static C++ objects,
    // logging setup) have no preconditions on the loading process.
    let lib = unsafe { Library::new(path) }.map_err(|e| RealSenseError::LibraryNotFound {
        tried: path.display().to_string(),
        why: e.to_string(),
    })?;
    macro_rules! sym {
        ($name:literal) => {{
            // SAFETY: the pointer type is the C declaration of this rs2_ function (see the
            // module docs); the library stays loaded for the life of the process.
            let s = unsafe { lib.get(concat!($name, "\0").as_bytes()) }.map_err(|e| {
                RealSenseError::MissingSymbol {
                    library: path.display().to_string(),
                    symbol: $name,
                    why: e.to_string(),
                }
            })?;
            *s
        }};
    }
    Ok(Api {
        get_api_version: sym!("rs2_get_api_version"),
        get_error_message: sym!("rs2_get_error_message"),
        get_failed_function: sym!("rs2_get_failed_function"),
        free_error: sym!("rs2_free_error"),
        create_context: sym!("rs2_create_context"),
        delete_context: sym!("rs2_delete_context"),
        query_devices: sym!("rs2_query_devices"),
        get_device_count: sym!("rs2_get_device_count"),
        delete_device_list: sym!("rs2_delete_device_list"),
        create_device: sym!("rs2_create_device"),
        delete_device: sym!("rs2_delete_device"),
        supports_device_info: sym!("rs2_supports_device_info"),
        get_device_info: sym!("rs2_get_device_info"),
        create_config: sym!("rs2_create_config"),
        delete_config: sym!("rs2_delete_config"),
        config_enable_stream: sym!("rs2_config_enable_stream"),
        config_enable_device: sym!("rs2_config_enable_device"),
        config_enable_device_from_file_repeat_option: sym!(
            "rs2_config_enable_device_from_file_repeat_option"
        ),
        config_resolve: sym!("rs2_config_resolve"),
        create_pipeline: sym!("rs2_create_pipeline"),
        delete_pipeline: sym!("rs2_delete_pipeline"),
        pipeline_start_with_config: sym!("rs2_pipeline_start_with_config"),
        pipeline_stop: sym!("rs2_pipeline_stop"),
        pipeline_try_wait_for_frames: sym!("rs2_pipeline_try_wait_for_frames"),
        pipeline_profile_get_device: sym!("rs2_pipeline_profile_get_device"),
        pipeline_profile_get_streams: sym!("rs2_pipeline_profile_get_streams"),
        delete_pipeline_profile: sym!("rs2_delete_pipeline_profile"),
        get_stream_profiles_count: sym!("rs2_get_stream_profiles_count"),
        get_stream_profile: sym!("rs2_get_stream_profile"),
        delete_stream_profiles_list: sym!("rs2_delete_stream_profiles_list"),
        get_stream_profile_data: sym!("rs2_get_stream_profile_data"),
        get_video_stream_intrinsics: sym!("rs2_get_video_stream_intrinsics"),
        playback_device_set_real_time: sym!("rs2_playback_device_set_real_time"),
        playback_device_pause: sym!("rs2_playback_device_pause"),
        embedded_frames_count: sym!("rs2_embedded_frames_count"),
        extract_frame: sym!("rs2_extract_frame"),
        release_frame: sym!("rs2_release_frame"),
        get_frame_stream_profile: sym!("rs2_get_frame_stream_profile"),
        get_frame_data: sym!("rs2_get_frame_data"),
        get_frame_width: sym!("rs2_get_frame_width"),
        get_frame_height: sym!("rs2_get_frame_height"),
        get_frame_stride_in_bytes: sym!("rs2_get_frame_stride_in_bytes"),
        get_frame_bits_per_pixel: sym!("rs2_get_frame_bits_per_pixel"),
        get_frame_timestamp: sym!("rs2_get_frame_timestamp"),
        depth_frame_get_units: sym!("rs2_depth_frame_get_units"),
        frame_add_ref: sym!("rs2_frame_add_ref"),
        create_align: sym!("rs2_create_align"),
        delete_processing_block: sym!("rs2_delete_processing_block"),
        create_frame_queue: sym!("rs2_create_frame_queue"),
        delete_frame_queue: sym!("rs2_delete_frame_queue"),
        start_processing_queue: sym!("rs2_start_processing_queue"),
        process_frame: sym!("rs2_process_frame"),
        poll_for_frame: sym!("rs2_poll_for_frame"),
        _lib: lib,
    })
}

/// The candidates in search order: `EQUACT_LIBREALSENSE` alone when set, else the
/// versioned and the development names on the dynamic linker's path.
fn candidates() -> Vec<PathBuf> {
    match std::env::var_os(LIBRARY_ENV) {
        Some(p) if !p.is_empty() => vec![PathBuf::from(p)],
        _ => vec![
            PathBuf::from("librealsense2.so.2"),
            PathBuf::from("librealsense2.so"),
        ],
    }
}

/// Loads the library once per process: from `path` when given, else from the search order
/// of [`candidates`]. A later call with a different explicit path is refused.
fn api(path: Option<&Path>) -> Result<&'static Api, RealSenseError> {
    let _guard = LOADING.lock().unwrap_or_else(|p| p.into_inner());
    if let Some((from, api)) = API.get() {
        return match path {
            Some(p) if p != from => Err(RealSenseError::AlreadyLoaded {
                loaded: from.display().to_string(),
                requested: p.display().to_string(),
            }),
            _ => Ok(api),
        };
    }
    let tried = path.map_or_else(candidates, |p| vec![p.to_path_buf()]);
    let mut failures = Vec::new();
    for p in &tried {
        match load_from(p) {
            Ok(api) => {
                let major = {
                    let v = call!(&api, get_api_version())
                        .map_err(|e| RealSenseError::call(&e, "reading the version"))?;
                    v / 10000
                };
                if major != 2 {
                    return Err(RealSenseError::Version {
                        library: p.display().to_string(),
                        major,
                    });
                }
                let (_, api) = API.get_or_init(|| (p.clone(), api));
                return Ok(api);
            }
            Err(RealSenseError::LibraryNotFound { why, .. }) => failures.push(why),
            Err(e) => return Err(e),
        }
    }
    Err(RealSenseError::LibraryNotFound {
        tried: tried
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(", "),
        why: failures.join("; "),
    })
}

/// Loads librealsense2 from `path` (or the default search when `None`) and returns its API
/// version as `major * 10000 + minor * 100 + patch`.
pub fn load(path: Option<&Path>) -> Result<(PathBuf, i32), RealSenseError> {
    let api = api(path)?;
    let v = call!(api, get_api_version()).map_err(|e| RealSenseError::call(&e, "version"))?;
    let from = API.get().map(|(p, _)| p.clone()).unwrap_or_default();
    Ok((from, v))
}

/// Loads a shared library with its symbols visible to libraries loaded later
/// (`RTLD_GLOBAL`), and keeps it loaded: for a librealsense whose own dependencies are not
/// on the dynamic linker's path (the pyrealsense2 wheel needs libusb and libpython).
pub fn preload_global(path: &Path) -> Result<(), RealSenseError> {
    use libloading::os::unix::{Library as UnixLibrary, RTLD_GLOBAL, RTLD_NOW};
    // SAFETY: loading runs the library's initialisers; the callers preload plain C
    // libraries (libusb, libpython without initialising the interpreter).
    let lib = unsafe { UnixLibrary::open(Some(path), RTLD_NOW | RTLD_GLOBAL) }.map_err(|e| {
        RealSenseError::LibraryNotFound {
            tried: path.display().to_string(),
            why: e.to_string(),
        }
    })?;
    // Unloading could pull symbols from under librealsense: keep it for the process.
    std::mem::forget(lib);
    Ok(())
}

/// A librealsense context. The one for live devices lives for the process; a recording
/// plays in a context of its own (librealsense lists a playing recording among its
/// context's devices), deleted after its pipeline.
pub struct Context {
    api: &'static Api,
    raw: *mut RsContext,
}

// SAFETY: a librealsense context is internally synchronised (its device list and
// playback-device registry are locked), and this handle is never deleted.
unsafe impl Send for Context {}
// SAFETY: as above: every C call made through `&Context` is thread-safe.
unsafe impl Sync for Context {}

/// The context for live devices.
static LIVE: OnceLock<Context> = OnceLock::new();

impl Context {
    /// The context for live devices, created on first use (this starts librealsense's
    /// device watcher thread) and kept for the process.
    pub fn live() -> Result<&'static Self, RealSenseError> {
        Self::get(&LIVE)
    }

    fn get(cell: &'static OnceLock<Context>) -> Result<&'static Self, RealSenseError> {
        let api = api(None)?;
        let _guard = LOADING.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(ctx) = cell.get() {
            return Ok(ctx);
        }
        let raw = call!(api, create_context(API_VERSION))
            .map_err(|e| RealSenseError::call(&e, "creating a context"))?;
        Ok(cell.get_or_init(|| Self { api, raw }))
    }

    /// (serial, name) of every connected device.
    pub fn devices(&self) -> Result<Vec<(String, String)>, Rs2Error> {
        let api = self.api;
        let list = call!(api, query_devices(self.raw))?;
        let list = Owned(list, api.delete_device_list);
        let n = call!(api, get_device_count(list.0))?;
        let mut out = Vec::new();
        for i in 0..n {
            let dev = Owned(call!(api, create_device(list.0, i))?, api.delete_device);
            let info = |what: c_int| -> Result<String, Rs2Error> {
                if call!(api, supports_device_info(dev.0, what))? == 0 {
                    return Ok(String::new());
                }
                Ok(c_text(call!(api, get_device_info(dev.0, what))?))
            };
            out.push((info(INFO_SERIAL_NUMBER)?, info(INFO_NAME)?));
        }
        Ok(out)
    }
}

/// A context owned by one pipeline (a recording's).
pub struct OwnedContext(Context);

impl OwnedContext {
    /// Creates a context.
    pub fn new() -> Result<Self, RealSenseError> {
        let api = api(None)?;
        let raw = call!(api, create_context(API_VERSION))
            .map_err(|e| RealSenseError::call(&e, "creating a context"))?;
        Ok(Self(Context { api, raw }))
    }
}

impl Drop for OwnedContext {
    fn drop(&mut self) {
        // SAFETY: `raw` came from rs2_create_context and is deleted once, after the
        // pipeline made from it (the pipeline's drop runs before its fields').
        unsafe { (self.0.api.delete_context)(self.0.raw) }
    }
}

/// A handle with its deleter.
struct Owned<T>(*mut T, unsafe extern "C" fn(*mut T));

impl<T> Drop for Owned<T> {
    fn drop(&mut self) {
        if !self.0.is_null() {
            // SAFETY: the pointer came from the matching rs2_create/query call and is
            // deleted once.
            unsafe { (self.1)(self.0) }
        }
    }
}

/// What a pipeline should stream from.
pub enum Source<'a> {
    /// The connected device with this serial.
    Device(&'a str),
    /// A recording, played once, as fast as frames are taken.
    File(&'a Path),
}

/// One stream to enable: (stream, index, width, height, format, fps).
pub type StreamRequest = (c_int, c_int, c_int, c_int, c_int, c_int);

/// Stream type, format and index of a stream profile, with its intrinsics.
#[derive(Copy, Clone, Debug)]
pub struct ProfileInfo {
    /// `rs2_stream`.
    pub stream: c_int,
    /// `rs2_format`.
    pub format: c_int,
    /// Stream index (infrared 1 is the left imager).
    pub index: c_int,
    /// Frame rate (Hz).
    pub fps: c_int,
    /// Intrinsics.
    pub intrinsics: RsIntrinsics,
}

fn profile_info(api: &Api, p: *const RsStreamProfile) -> Result<ProfileInfo, Rs2Error> {
    let (mut stream, mut format, mut index, mut uid, mut fps) = (0, 0, 0, 0, 0);
    call!(
        api,
        get_stream_profile_data(p, &mut stream, &mut format, &mut index, &mut uid, &mut fps)
    )?;
    let mut intrinsics = RsIntrinsics::default();
    call!(api, get_video_stream_intrinsics(p, &mut intrinsics))?;
    Ok(ProfileInfo {
        stream,
        format,
        index,
        fps,
        intrinsics,
    })
}

/// A C string argument.
fn text(s: &str) -> Result<CString, Rs2Error> {
    CString::new(s).map_err(|_| Rs2Error {
        function: "equact".into(),
        message: format!("{s:?} contains a NUL byte"),
    })
}

/// Configures `pipe` for `source` and `streams` and starts it.
fn configure_and_start(
    api: &Api,
    pipe: *mut RsPipeline,
    source: Source<'_>,
    streams: &[StreamRequest],
) -> Result<*mut RsPipelineProfile, Rs2Error> {
    let config = Owned(call!(api, create_config())?, api.delete_config);
    match source {
        Source::Device(serial) => {
            let serial = text(serial)?;
            call!(api, config_enable_device(config.0, serial.as_ptr()))?;
        }
        Source::File(path) => {
            let file = text(&path.to_string_lossy())?;
            call!(
                api,
                config_enable_device_from_file_repeat_option(config.0, file.as_ptr(), 0)
            )?;
            // Playback is real time by default: frames a slow reader misses are dropped.
            // Resolving first creates the context's playback device, which the start
            // below reuses, so it is non-real-time from the first frame.
            let pre = Owned(
                call!(api, config_resolve(config.0, pipe))?,
                api.delete_pipeline_profile,
            );
            let dev = Owned(
                call!(api, pipeline_profile_get_device(pre.0))?,
                api.delete_device,
            );
            call!(api, playback_device_set_real_time(dev.0, 0))?;
        }
    }
    for &(stream, index, w, h, format, fps) in streams {
        call!(
            api,
            config_enable_stream(config.0, stream, index, w, h, format, fps)
        )?;
    }
    call!(api, pipeline_start_with_config(pipe, config.0))
}

/// A started pipeline; dropping it stops the streams.
pub struct Pipeline {
    api: &'static Api,
    raw: *mut RsPipeline,
    profile: *mut RsPipelineProfile,
    /// A recording's own context, deleted after the pipeline.
    _owned: Option<OwnedContext>,
}

// SAFETY: librealsense pipelines may be used from any thread (one at a time, which
// `&mut self` guarantees); the handles are owned here.
unsafe impl Send for Pipeline {}

impl Pipeline {
    /// Starts a pipeline on `source` with `streams`.
    /// A librealsense failure of the start itself goes through `failed`.
    pub fn start(
        source: Source<'_>,
        streams: &[StreamRequest],
        failed: impl FnOnce(Rs2Error) -> RealSenseError,
    ) -> Result<Self, RealSenseError> {
        let owned = match source {
            Source::File(_) => Some(OwnedContext::new()?),
            Source::Device(_) => None,
        };
        let ctx = match &owned {
            Some(o) => &o.0,
            None => Context::live()?,
        };
        let (api, raw, profile) = Self::start_in(ctx, source, streams).map_err(failed)?;
        Ok(Self {
            api,
            raw,
            profile,
            _owned: owned,
        })
    }

    /// Creates and starts a pipeline in `ctx`; returns the raw handles.
    #[allow(clippy::type_complexity)]
    fn start_in(
        ctx: &Context,
        source: Source<'_>,
        streams: &[StreamRequest],
    ) -> Result<(&'static Api, *mut RsPipeline, *mut RsPipelineProfile), Rs2Error> {
        let api = ctx.api;
        let _lifecycle = LIFECYCLE.lock().unwrap_or_else(|p| p.into_inner());
        let raw = Owned(call!(api, create_pipeline(ctx.raw))?, api.delete_pipeline);
        let profile = configure_and_start(api, raw.0, source, streams)?;
        let pipe = raw.0;
        // The pipeline owns the handle now.
        std::mem::forget(raw);
        Ok((api, pipe, profile))
    }

    /// The streams the pipeline runs.
    pub fn streams(&self) -> Result<Vec<ProfileInfo>, Rs2Error> {
        let api = self.api;
        let list = Owned(
            call!(api, pipeline_profile_get_streams(self.profile))?,
            api.delete_stream_profiles_list,
        );
        let n = call!(api, get_stream_profiles_count(list.0))?;
        (0..n)
            .map(|i| profile_info(api, call!(api, get_stream_profile(list.0, i))?))
            .collect()
    }

    /// The next frameset, or `None` when none arrived within `timeout_ms`.
    pub fn try_wait(&mut self, timeout_ms: u32) -> Result<Option<Frame>, Rs2Error> {
        let mut frame: *mut RsFrame = ptr::null_mut();
        let got = call!(
            self.api,
            pipeline_try_wait_for_frames(self.raw, &mut frame, timeout_ms)
        )?;
        if got == 0 || frame.is_null() {
            return Ok(None);
        }
        Ok(Some(Frame {
            api: self.api,
            raw: frame,
        }))
    }
}

impl Drop for Pipeline {
    fn drop(&mut self) {
        let api = self.api;
        let _lifecycle = LIFECYCLE.lock().unwrap_or_else(|p| p.into_inner());
        // A recording's playback device, when this pipeline plays one.
        let playback = match self._owned {
            Some(_) => match call!(api, pipeline_profile_get_device(self.profile)) {
                Ok(d) => Some(Owned(d, api.delete_device)),
                Err(e) => {
                    log::warn!("finding the RealSense playback device: {e}");
                    None
                }
            },
            None => None,
        };
        if let Err(e) = call!(api, pipeline_stop(self.raw)) {
            log::warn!("stopping the RealSense pipeline: {e}");
        }
        // The stop hands the playback's own stop (which reopens the file) to the
        // recording's reader thread without waiting for it, and deleting the device under
        // it corrupted the heap now and then (valgrind: ros2_reader_base::reset after
        // ~playback_device). Pausing runs on that thread and waits for it, so it is the
        // barrier. (Not before the stop: with the pipeline's queue full and nobody taking
        // frames, the pause waits on a reader that waits on the queue, until timeouts.)
        if let Some(dev) = &playback {
            if let Err(e) = call!(api, playback_device_pause(dev.0)) {
                log::warn!("waiting for the RealSense playback to stop: {e}");
            }
        }
        drop(playback);
        // SAFETY: the profile came from rs2_pipeline_start_with_config; deleted once.
        unsafe { (api.delete_pipeline_profile)(self.profile) };
        // SAFETY: the pipeline came from rs2_create_pipeline; deleted once, after stop.
        unsafe { (api.delete_pipeline)(self.raw) };
    }
}

/// librealsense's `align` processing block to the depth stream, with its output queue.
/// It runs on the calling thread inside `rs2_process_frame`.
pub struct Align {
    api: &'static Api,
    block: *mut RsProcessingBlock,
    queue: *mut RsFrameQueue,
}

// SAFETY: the block and queue are owned here and used through `&mut self` only.
unsafe impl Send for Align {}

impl Align {
    /// An align-to-depth block (the library must be loaded: a pipeline exists).
    pub fn to_depth() -> Result<Self, RealSenseError> {
        let api = api(None)?;
        let err = |e: Rs2Error| RealSenseError::call(&e, "creating the align-to-depth block");
        let block = Owned(
            call!(api, create_align(STREAM_DEPTH)).map_err(err)?,
            api.delete_processing_block,
        );
        let queue = Owned(
            call!(api, create_frame_queue(1)).map_err(err)?,
            api.delete_frame_queue,
        );
        call!(api, start_processing_queue(block.0, queue.0)).map_err(err)?;
        let out = Self {
            api,
            block: block.0,
            queue: queue.0,
        };
        // `out` owns both handles now.
        std::mem::forget(block);
        std::mem::forget(queue);
        Ok(out)
    }

    /// The frameset with its colour frame resampled onto the depth pixels.
    pub fn process(&mut self, set: &Frame) -> Result<Option<Frame>, Rs2Error> {
        let api = self.api;
        // rs2_process_frame takes over one reference: give it its own.
        call!(api, frame_add_ref(set.raw))?;
        call!(api, process_frame(self.block, set.raw))?;
        let mut out: *mut RsFrame = ptr::null_mut();
        let got = call!(api, poll_for_frame(self.queue, &mut out))?;
        if got == 0 || out.is_null() {
            return Ok(None);
        }
        Ok(Some(Frame { api, raw: out }))
    }
}

impl Drop for Align {
    fn drop(&mut self) {
        // SAFETY: both came from their rs2_create_ calls and are deleted once, the block
        // (which writes into the queue) first.
        unsafe {
            (self.api.delete_processing_block)(self.block);
            (self.api.delete_frame_queue)(self.queue);
        }
    }
}

/// A frame or frameset reference; released on drop.
pub struct Frame {
    api: &'static Api,
    raw: *mut RsFrame,
}

/// Pixels of one video frame, copied out row by row.
pub struct Pixels {
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Bytes per pixel.
    pub bytes_per_pixel: usize,
    /// `width * height * bytes_per_pixel` bytes, rows packed (stride removed).
    pub bytes: Vec<u8>,
}

impl Frame {
    /// The frames inside a frameset.
    pub fn parts(&self) -> Result<Vec<Frame>, Rs2Error> {
        let api = self.api;
        let n = call!(api, embedded_frames_count(self.raw))?;
        (0..n)
            .map(|i| {
                let raw = call!(api, extract_frame(self.raw, i))?;
                Ok(Frame { api, raw })
            })
            .collect()
    }

    /// The stream profile of this frame.
    pub fn profile(&self) -> Result<ProfileInfo, Rs2Error> {
        let p = call!(self.api, get_frame_stream_profile(self.raw))?;
        profile_info(self.api, p)
    }

    /// Timestamp (ms) in the frame's time domain.
    pub fn timestamp_ms(&self) -> Result<f64, Rs2Error> {
        call!(self.api, get_frame_timestamp(self.raw))
    }

    /// Metres per depth unit of a depth frame.
    pub fn depth_units(&self) -> Result<f32, Rs2Error> {
        call!(self.api, depth_frame_get_units(self.raw))
    }

    /// Copies the pixels out.
    pub fn pixels(&self) -> Result<Pixels, Rs2Error> {
        let api = self.api;
        let w = call!(api, get_frame_width(self.raw))?;
        let h = call!(api, get_frame_height(self.raw))?;
        let stride = call!(api, get_frame_stride_in_bytes(self.raw))?;
        let bpp = call!(api, get_frame_bits_per_pixel(self.raw))?;
        let data = call!(api, get_frame_data(self.raw))?;
        let bad = |what: String| Rs2Error {
            function: "equact".into(),
            message: what,
        };
        let (Ok(w), Ok(h), Ok(stride), Ok(bpp)) = (
            usize::try_from(w),
            usize::try_from(h),
            usize::try_from(stride),
            usize::try_from(bpp),
        ) else {
            return Err(bad(format!(
                "frame reports a negative size: {w}x{h}, stride {stride}, {bpp} bits per pixel"
            )));
        };
        let bytes_per_pixel = bpp / 8;
        let row = w * bytes_per_pixel;
        if bpp % 8 != 0 || stride < row || data.is_null() {
            return Err(bad(format!(
                "unusable frame layout: {w}x{h}, stride {stride}, {bpp} bits per pixel"
            )));
        }
        // SAFETY: librealsense guarantees `stride * height` readable bytes at `data` while
        // the frame reference (`self`) is held; the slice does not outlive this function.
        let all = unsafe { std::slice::from_raw_parts(data.cast::<u8>(), stride * h) };
        let mut bytes = Vec::with_capacity(row * h);
        for r in all.chunks_exact(stride).take(h) {
            bytes.extend_from_slice(&r[..row]);
        }
        Ok(Pixels {
            width: w as u32,
            height: h as u32,
            bytes_per_pixel,
            bytes,
        })
    }
}

impl Drop for Frame {
    fn drop(&mut self) {
        // SAFETY: `raw` is a reference we own (from try_wait or extract_frame); released once.
        unsafe { (self.api.release_frame)(self.raw) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_library_says_how_to_install_it() {
        let Err(e) = load_from(Path::new("/nonexistent/librealsense2.so")) else {
            panic!("loaded a file that does not exist");
        };
        assert!(matches!(e, RealSenseError::LibraryNotFound { .. }), "{e:?}");
        let text = e.to_string();
        assert!(text.contains("librealsense2-dev"), "{text}");
        assert!(text.contains("EQUACT_LIBREALSENSE="), "{text}");
    }

    #[test]
    fn a_library_that_is_not_librealsense_is_named() {
        // libc is loaded in every process and has no rs2_ functions.
        let Err(e) = load_from(Path::new("libc.so.6")) else {
            panic!("libc passed for librealsense");
        };
        assert!(
            matches!(
                e,
                RealSenseError::MissingSymbol {
                    symbol: "rs2_get_api_version",
                    ..
                }
            ),
            "{e:?}"
        );
    }
}
