//! Scene-reconstruction exports for Gaussian-splatting trainers (paper §5, `fig:eval-gs`): the
//! wrist lenses' frames sampled at about one per second, each posed on the session timeline from
//! the episode's outputs, the lenses as OpenCV fisheye cameras, and the visual maps' landmarks in
//! the scene frame as initial points. Written as a COLMAP text model (3DGUT, gsplat) or a
//! nerfstudio `transforms.json` (nerfstudio, brush).
//!
//! Poses: an image is posed at its centre row's exposure, the rolling-shutter frame's one
//! global-shutter stand-in: its frame timestamp (the first row's exposure, where the outputs
//! pair each front frame with its fused pose) plus half the recording mode's readout from the
//! unit's calibration. A front image takes the outputs' `scene_from_front_cam` interpolated to
//! that time; any other lens of the unit the same trajectory at its own time shifted by the
//! lenses' time-shift difference, composed with `front_from_lens = front_from_imu ·
//! lens_from_imu⁻¹`.
//! Lenses of one unit exposed together are one rig frame, so front and rear stay one rigid body.
//! The head camera's (ego) images, when the session has one, are posed from the outputs'
//! `head.csv` (the hat marker's track through the head mount) at their centre row's exposure;
//! the head camera is a rig of its own.
//!
//! Every image gets a mask ([`super::mask`]) of the tool's parts at the frame's gripper opening
//! (wrist lenses) and of the camera body at the rim of the lens field.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use image::ImageEncoder as _;
use nalgebra::{DMatrix, DVector, Point2, Vector3};
use serde::Serialize;

use kiwi_core::artifact::UnitCalibration;
use kiwi_core::camera::{Camera, CameraModel, DoubleSphere, Kb4, bearing_from_angles};
use kiwi_core::geometry::Pose;
use kiwi_core::io::write_atomic;
use kiwi_core::layout::{EpisodeLayout, Side};
use kiwi_core::tool::ToolDefinition;

use super::mask::{LensMasker, mask_openings};
use super::{
    ExportOptions, ExportReport, SessionExport, View, ViewStream, choose_rate, episode_grid,
    export_err, resolve_views, source_rates,
};
use crate::error::{BackendError, Result};
use crate::formats::calibration::exposure_centre_delay;
use crate::outputs::SupportClass;
use crate::pipeline::graph::MapName;
use crate::pipeline::stages::map_in_scene;
use crate::vision::map::VisualMap;

/// Images per second and lens stream when none is asked for: splatting wants views from many
/// places, not many views from one place (the hand moves ~0.5 m/s).
pub const DEFAULT_RATE_HZ: f64 = 1.0;
/// Every this many time groups one is held out as test views (the paper's split, as
/// Mip-NeRF 360's `llffhold`).
pub const SPLIT_EVERY: usize = 8;
/// Largest error (px) a Double Sphere lens may have as a refitted KB4 model: below the
/// corner-detection noise of a calibration, so the refit adds nothing a trainer would notice.
pub const MAX_REFIT_ERROR_PX: f64 = 0.1;
/// Lenses of one unit whose exposures (after their time shifts) are this close form one rig
/// frame: 0.5 ms moves a hand at 1 m/s by 0.5 mm.
const RIG_SYNC_TOL_S: f64 = 5e-4;
/// Directions sampled along the valid field for a refit.
const REFIT_SAMPLES: usize = 400;
/// COLMAP and nerfstudio put the first pixel's centre at 0.5; KIWI at 0.
pub const PIXEL_CENTRE_OFFSET: f64 = 0.5;
/// Colour of an initial point no exported image observes (the maps store no colour): mid grey.
const POINT_GREY: u8 = 128;
/// Folder of the exported images.
pub const IMAGES_DIR: &str = "images";
/// Folder of the COLMAP model, where COLMAP's own tools and the trainers look for it.
pub const COLMAP_MODEL_DIR: &str = "sparse/0";
/// Image names of the held-out views, one per line.
pub const TEST_LIST: &str = "test.txt";
/// Image names of the training views, one per line.
pub const TRAIN_LIST: &str = "train.txt";
/// The export's own record: lenses, refits, counts.
pub const SUMMARY_FILE: &str = "kiwi_export.json";
/// Ending of a mask's name: 3DGUT reads `<image stem>_mask.png` beside each image.
pub const MASK_SUFFIX: &str = "_mask.png";
/// nerfstudio's initial points.
pub const PLY_FILE: &str = "points3D.ply";

/// Which trainer format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SceneFormat {
    /// COLMAP text model (`cameras.txt`, `images.txt`, `points3D.txt`, `rigs.txt`, `frames.txt`).
    Colmap,
    /// nerfstudio `transforms.json` with `points3D.ply`.
    Nerfstudio,
}

/// How well a Double Sphere lens is represented by its refitted KB4 model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Refit {
    /// Largest pixel distance between the two models over the fitted field (px).
    pub max_px: f64,
    /// RMS pixel distance (px).
    pub rms_px: f64,
    /// Half-angle of the fitted field (rad).
    pub max_theta_rad: f64,
}

/// A lens as COLMAP's `OPENCV_FISHEYE` camera: `[fx, fy, cx, cy, k1, k2, k3, k4]` with the
/// principal point in COLMAP's pixel convention (first pixel centre at 0.5).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FisheyeCamera {
    /// Width (px).
    pub width: u32,
    /// Height (px).
    pub height: u32,
    /// Parameters in COLMAP's order and pixel convention.
    pub params: [f64; 8],
    /// The refit, when the lens was calibrated as Double Sphere.
    pub refit: Option<Refit>,
}

/// A calibrated lens as an OpenCV fisheye camera: KB4 as it is (the principal point moved to
/// COLMAP's pixel convention), Double Sphere refitted to KB4 over `valid_fov_rad`. A refit
/// worse than [`MAX_REFIT_ERROR_PX`] is an error saying by how much.
pub fn opencv_fisheye(
    camera: &Camera,
    valid_fov_rad: f64,
) -> std::result::Result<FisheyeCamera, String> {
    let (width, height) = camera.resolution();
    let (kb4, refit) = match camera {
        Camera::Kb4(c) => (c.clone(), None),
        Camera::DoubleSphere(ds) => {
            let (kb4, refit) = refit_kb4(ds, 0.5 * valid_fov_rad)?;
            if refit.max_px > MAX_REFIT_ERROR_PX {
                return Err(format!(
                    "the Double Sphere lens cannot be written as OPENCV_FISHEYE: its best KB4 fit \
                     over the valid field (±{:.1}°) is off by up to {:.3} px (allowed \
                     {MAX_REFIT_ERROR_PX} px); calibrate the lens as kb4 (`kiwi-calib intrinsics \
                     --model kb4`)",
                    refit.max_theta_rad.to_degrees(),
                    refit.max_px
                ));
            }
            (kb4, Some(refit))
        }
    };
    let mut params = [0.0; 8];
    params.copy_from_slice(kb4.params());
    params[2] += PIXEL_CENTRE_OFFSET;
    params[3] += PIXEL_CENTRE_OFFSET;
    Ok(FisheyeCamera {
        width,
        height,
        params,
        refit,
    })
}

/// The KB4 model closest to a Double Sphere lens over directions up to `max_theta` off-axis:
/// same principal point, focal lengths scaled, the radial polynomial fitted by least squares to
/// the Double Sphere's normalized radius (both models are radial in normalized coordinates).
fn refit_kb4(ds: &DoubleSphere, max_theta: f64) -> std::result::Result<(Kb4, Refit), String> {
    let p = ds.params();
    let (fx, cx) = (p[0], p[2]);
    let mut samples = Vec::with_capacity(REFIT_SAMPLES);
    for i in 1..=REFIT_SAMPLES {
        let theta = max_theta * i as f64 / REFIT_SAMPLES as f64;
        let Some(px) = ds.project(&bearing_from_angles(theta, 0.0)) else {
            return Err(format!(
                "the Double Sphere lens does not project the direction {:.1}° off its axis, \
                 inside its valid field (±{:.1}°); check valid_fov_rad in its calibration",
                theta.to_degrees(),
                max_theta.to_degrees()
            ));
        };
        samples.push((theta, (px.x - cx) / fx));
    }
    let a = DMatrix::from_fn(samples.len(), 5, |r, c| samples[r].0.powi(2 * c as i32 + 1));
    let b = DVector::from_iterator(samples.len(), samples.iter().map(|s| s.1));
    let x = a
        .svd(true, true)
        .solve(&b, 1e-15)
        .map_err(|e| format!("the KB4 refit of a Double Sphere lens failed: {e}"))?;
    let scale = x[0];
    if !(scale.is_finite() && scale > 0.0) {
        return Err("the KB4 refit of a Double Sphere lens has no positive focal length".into());
    }
    let (width, height) = ds.resolution();
    let kb4 = Kb4::new(
        width,
        height,
        [
            p[0] * scale,
            p[1] * scale,
            p[2],
            p[3],
            x[1] / scale,
            x[2] / scale,
            x[3] / scale,
            x[4] / scale,
        ],
    )
    .map_err(|e| format!("the KB4 refit of a Double Sphere lens is not a valid lens: {e}"))?;
    // Both models are radial in normalized coordinates: one azimuth measures every one.
    let (mut worst, mut sum2, mut n) = (0.0f64, 0.0, 0usize);
    for &(theta, _) in &samples {
        let d = bearing_from_angles(theta, 0.0);
        let err = match (ds.project(&d), kb4.project(&d)) {
            (Some(a), Some(b)) => (a - b).norm(),
            _ => f64::INFINITY,
        };
        worst = worst.max(err);
        sum2 += err * err;
        n += 1;
    }
    Ok((
        kb4,
        Refit {
            max_px: worst,
            rms_px: (sum2 / n.max(1) as f64).sqrt(),
            max_theta_rad: max_theta,
        },
    ))
}

/// A lens stream that is exported: of a wrist unit, or the head camera's.
struct Lens {
    view: View,
    /// The wrist (`None` for the head camera).
    side: Option<Side>,
    camera_id: u32,
    model: Camera,
    /// The unit's `calibration.json` (named when a stream does not fit it).
    calibration_path: std::path::PathBuf,
    fisheye: FisheyeCamera,
    /// `front_from_lens` (identity for the front lens and the head camera).
    front_from_lens: Pose,
    /// This lens's time shift minus the front lens's (s).
    shift_from_front_s: f64,
    /// The unit's tool (the parts masked out of its images; none on the head camera).
    tool: Option<ToolDefinition>,
    /// The unit's calibration (its recording modes' readout times).
    calibration: UnitCalibration,
    /// Per-pixel rays for the masks.
    masker: LensMasker,
}

/// One exported image.
struct SceneImage {
    id: u32,
    lens: usize,
    name: String,
    scene_from_cam: Pose,
    /// The mask's name beside the image (`<frame>_mask.png`).
    mask_name: String,
    /// `(pixel in COLMAP's convention, point id)`.
    points2d: Vec<([f64; 2], u64)>,
    test: bool,
}

/// Images of one unit exposed together.
struct RigFrame {
    id: u32,
    rig: usize,
    /// `ref_from_scene` of the rig's reference lens.
    ref_from_scene: Pose,
    images: Vec<u32>,
}

/// A unit's lenses as one rigid body; the first lens is the reference.
struct Rig {
    /// The wrist (`None` for the head camera).
    side: Option<Side>,
    lenses: Vec<usize>,
}

/// A map landmark in the scene frame.
struct ScenePoint {
    xyz: Vector3<f64>,
    /// `(image id, index in the image's points2d)`.
    track: Vec<(u32, usize)>,
    error_px: f64,
    /// Mean colour of its observations in the exported images; grey when none was exported.
    rgb: [u8; 3],
}

/// Everything a scene export writes.
struct Scene {
    lenses: Vec<Lens>,
    rigs: Vec<Rig>,
    frames: Vec<RigFrame>,
    images: Vec<SceneImage>,
    points: BTreeMap<u64, ScenePoint>,
    /// Per point id: the summed RGB of its observations in the written images and their count.
    colour_sums: BTreeMap<u64, ([u64; 3], u64)>,
}

#[derive(Serialize)]
struct LensSummary {
    view: String,
    camera_id: u32,
    source_model: String,
    opencv_fisheye: FisheyeCamera,
}

#[derive(Serialize)]
struct Summary {
    schema_version: u32,
    format: &'static str,
    rate_hz: f64,
    pixel_convention: &'static str,
    scene_frame: &'static str,
    masks: &'static str,
    lenses: Vec<LensSummary>,
    images: usize,
    test_images: usize,
    points: usize,
    images_without_pose: usize,
    episodes: Vec<String>,
}

/// Write a session's scene-reconstruction export into `dir`.
pub fn write(
    exp: &SessionExport,
    options: &ExportOptions,
    format: SceneFormat,
    dir: &Path,
) -> Result<ExportReport> {
    let rate_hz = options.rate.unwrap_or(DEFAULT_RATE_HZ);
    let views = scene_views(exp, options)?;
    let mut lenses = open_lenses(exp, &views)?;
    let mut report = ExportReport::default();
    for l in &lenses {
        if let Some(r) = l.fisheye.refit {
            report.notes.push(format!(
                "lens {}.{}: Double Sphere refitted to OPENCV_FISHEYE over ±{:.1}°: error at most \
                 {:.4} px, RMS {:.4} px",
                l.view.camera,
                l.view.lens,
                r.max_theta_rad.to_degrees(),
                r.max_px,
                r.rms_px
            ));
        }
    }
    let rigs = rigs_of(&lenses);
    let maps = load_maps(exp)?;
    let mut scene = Scene {
        lenses: Vec::new(),
        rigs,
        frames: Vec::new(),
        images: Vec::new(),
        points: BTreeMap::new(),
        colour_sums: BTreeMap::new(),
    };
    let mut group = 0usize;
    let mut unposed = 0usize;
    for ep in &exp.episodes {
        let (groups, skipped) = pose_episode(
            ep,
            &lenses,
            &mut scene,
            &maps,
            rate_hz,
            group,
            dir,
            &mut report.notes,
        )?;
        group += groups;
        unposed += skipped;
        report.exported.push(ep.name.clone());
    }
    scene.lenses = std::mem::take(&mut lenses);
    fill_points(&mut scene, &maps);
    match format {
        SceneFormat::Colmap => write_colmap(&scene, dir)?,
        SceneFormat::Nerfstudio => write_nerfstudio(&scene, dir)?,
    }
    write_split(&scene, dir)?;
    let summary = Summary {
        schema_version: 1,
        format: match format {
            SceneFormat::Colmap => "colmap",
            SceneFormat::Nerfstudio => "nerfstudio",
        },
        rate_hz,
        pixel_convention: "COLMAP: the first pixel's centre is at (0.5, 0.5)",
        scene_frame: "KIWI's scene frame: metric, z up (against gravity), the session's rear map",
        masks: "images/<image stem>_mask.png: 255 where the pixel sees the scene, 0 on the tool's \
                jaws and tag (at the frame's gripper opening) and the camera body beyond the \
                lens's valid field",
        lenses: scene
            .lenses
            .iter()
            .map(|l| LensSummary {
                view: format!("{}.{}", l.view.camera, l.view.lens),
                camera_id: l.camera_id,
                source_model: l.model.kind().to_string(),
                opencv_fisheye: l.fisheye.clone(),
            })
            .collect(),
        images: scene.images.len(),
        test_images: scene.images.iter().filter(|i| i.test).count(),
        points: scene.points.len(),
        images_without_pose: unposed,
        episodes: report.exported.clone(),
    };
    let json = serde_json::to_vec_pretty(&summary)
        .map_err(|e| export_err(format!("cannot encode {SUMMARY_FILE}: {e}")))?;
    write_atomic(&dir.join(SUMMARY_FILE), &json)?;
    if unposed > 0 {
        report.notes.push(format!(
            "{unposed} sampled frame(s) left out: no visually supported pose at their time"
        ));
    }
    report.frames = scene.images.len();
    report.fps = Some(rate_hz);
    Ok(report)
}

/// The lens streams to export: those named, else every lens of every wrist camera and of the
/// head camera (when the session has one).
fn scene_views(exp: &SessionExport, options: &ExportOptions) -> Result<Vec<View>> {
    let Some(first) = exp.episodes.first() else {
        return Ok(Vec::new());
    };
    let requested: Vec<String> = match &options.views {
        Some(v) => v.clone(),
        None => {
            let layout = EpisodeLayout::new(&first.dir);
            let mut v = Vec::new();
            for side in exp.session.wrists.keys() {
                let camera = side.camera_name();
                let meta = layout.read_meta(camera)?;
                v.extend(meta.lenses.iter().map(|l| format!("{camera}.{l}")));
            }
            if exp.session.head.is_some() && layout.meta_json("head").is_file() {
                let meta = layout.read_meta("head")?;
                v.extend(meta.lenses.iter().map(|l| format!("head.{l}")));
            }
            v
        }
    };
    let views = resolve_views(exp, Some(requested.as_slice()))?;
    if let Some(v) = views.iter().find(|v| {
        !(exp
            .session
            .wrists
            .keys()
            .any(|s| s.camera_name() == v.camera)
            || (v.camera == "head" && exp.session.head.is_some()))
    }) {
        return Err(export_err(format!(
            "--views: {}.{} is neither a wrist lens nor the head camera's; only those have poses \
             in the outputs (leave it out)",
            v.camera, v.lens
        )));
    }
    Ok(views)
}

fn open_lenses(exp: &SessionExport, views: &[View]) -> Result<Vec<Lens>> {
    let mut lenses = Vec::new();
    for (side, cfg) in &exp.session.wrists {
        let path = exp.root.join(&cfg.calibration).join("calibration.json");
        let cal = UnitCalibration::load(&path)?;
        let input = |message: String| BackendError::Input {
            path: path.clone(),
            message,
        };
        let lens_cal = |name: &str| {
            let l = cal.lens(name).ok_or_else(|| {
                input(format!(
                    "no lens `{name}` in the unit's calibration; certify the unit with both lenses"
                ))
            })?;
            let cam_from_imu = l.cam_from_imu().ok_or_else(|| {
                input(format!(
                    "lens `{name}` has no cam_from_imu; run `kiwi-calib cam-imu` on the unit"
                ))
            })?;
            Ok::<_, BackendError>((l, cam_from_imu, l.time_shift_s.unwrap_or(0.0)))
        };
        let (_, front_from_imu, front_shift) = lens_cal("front")?;
        let tool = ToolDefinition::builtin(cfg.tool)?;
        for view in views.iter().filter(|v| v.camera == side.camera_name()) {
            let (l, lens_from_imu, shift) = lens_cal(&view.lens)?;
            let model = l.camera()?;
            let fisheye = opencv_fisheye(&model, l.valid_fov_rad)
                .map_err(|m| input(format!("lens `{}`: {m}", view.lens)))?;
            let front_from_lens = front_from_imu * lens_from_imu.inverse();
            let masker = LensMasker::new(&model, l.valid_fov_rad, front_from_lens.inverse());
            lenses.push(Lens {
                view: view.clone(),
                side: Some(*side),
                camera_id: lenses.len() as u32 + 1,
                model,
                calibration_path: path.clone(),
                fisheye,
                front_from_lens,
                shift_from_front_s: shift - front_shift,
                tool: Some(tool.clone()),
                calibration: cal.clone(),
                masker,
            });
        }
    }
    if let Some(head) = &exp.session.head {
        let path = exp.root.join(&head.calibration).join("calibration.json");
        for view in views.iter().filter(|v| v.camera == "head") {
            let cal = UnitCalibration::load(&path)?;
            let l = cal.lens(&view.lens).ok_or_else(|| BackendError::Input {
                path: path.clone(),
                message: format!(
                    "no lens `{}` in the head camera's calibration; certify it with that lens",
                    view.lens
                ),
            })?;
            let model = l.camera()?;
            let fisheye =
                opencv_fisheye(&model, l.valid_fov_rad).map_err(|m| BackendError::Input {
                    path: path.clone(),
                    message: format!("lens `{}`: {m}", view.lens),
                })?;
            let masker = LensMasker::new(&model, l.valid_fov_rad, Pose::identity());
            lenses.push(Lens {
                view: view.clone(),
                side: None,
                camera_id: lenses.len() as u32 + 1,
                model,
                calibration_path: path.clone(),
                fisheye,
                front_from_lens: Pose::identity(),
                shift_from_front_s: 0.0,
                tool: None,
                calibration: cal,
                masker,
            });
        }
    }
    Ok(lenses)
}

fn rigs_of(lenses: &[Lens]) -> Vec<Rig> {
    let mut rigs: Vec<Rig> = Vec::new();
    for (i, l) in lenses.iter().enumerate() {
        match rigs.iter_mut().find(|r| r.side == l.side) {
            Some(r) => r.lenses.push(i),
            None => rigs.push(Rig {
                side: l.side,
                lenses: vec![i],
            }),
        }
    }
    // The front lens is the reference where it is exported.
    for r in &mut rigs {
        if let Some(k) = r
            .lenses
            .iter()
            .position(|&i| lenses[i].view.lens == "front")
        {
            r.lenses.swap(0, k);
        }
    }
    rigs
}

/// A visual map with its landmarks in the scene frame.
struct SceneMap {
    map: VisualMap,
    scene_points: Vec<Vector3<f64>>,
    /// Id of landmark 0 in the export.
    first_id: u64,
}

fn load_maps(exp: &SessionExport) -> Result<Vec<SceneMap>> {
    let mut names = vec![MapName::Rear];
    names.extend(exp.session.wrists.keys().map(|s| MapName::Front(*s)));
    let mut maps = Vec::new();
    let mut next_id = 1u64;
    for name in names {
        let (map, scene_points) = map_in_scene(&exp.root, name)?;
        let first_id = next_id;
        next_id += scene_points.len() as u64;
        maps.push(SceneMap {
            map,
            scene_points,
            first_id,
        });
    }
    Ok(maps)
}

/// Time from a lens frame's timestamp (its first row) to its centre row's exposure in an
/// episode (s): half the rolling readout of the recording mode its camera recorded in, from the
/// unit's calibration; 0, with a note, when the calibration knows no readout for that mode.
fn lens_centre_delay(
    ep: &super::EpisodeOutputs,
    lens: &Lens,
    notes: &mut Vec<String>,
) -> Result<f64> {
    let meta = EpisodeLayout::new(&ep.dir).read_meta(&lens.view.camera)?;
    match exposure_centre_delay(&lens.calibration, &meta.mode, meta.fps) {
        Some(delay) => Ok(delay),
        None => {
            notes.push(format!(
                "episode {}: {}.{}: the calibration gives no readout time for recording mode {} \
                 ({} fps); its images are posed at their first row (global shutter)",
                ep.name, lens.view.camera, lens.view.lens, meta.mode, meta.fps
            ));
            Ok(0.0)
        }
    }
}

/// Sample, pose and write the images of one episode; returns the time groups used and the
/// sampled frames left out for want of a pose.
#[allow(clippy::too_many_arguments)]
fn pose_episode(
    ep: &super::EpisodeOutputs,
    lenses: &[Lens],
    scene: &mut Scene,
    maps: &[SceneMap],
    rate_hz: f64,
    first_group: usize,
    dir: &Path,
    notes: &mut Vec<String>,
) -> Result<(usize, usize)> {
    let streams = lenses
        .iter()
        .map(|l| ViewStream::open(ep, &l.view))
        .collect::<Result<Vec<_>>>()?;
    for (l, s) in lenses.iter().zip(&streams) {
        s.source
            .check_calibration_size(&l.model, &l.calibration_path, None)?;
    }
    let centre_delays = lenses
        .iter()
        .map(|l| lens_centre_delay(ep, l, notes))
        .collect::<Result<Vec<f64>>>()?;
    let rate = choose_rate(Some(rate_hz), &source_rates(ep, &streams), &ep.name)?;
    let grid = episode_grid(ep, &streams, rate)?;
    let times = grid.times();
    let picks: Vec<Vec<usize>> = streams.iter().map(|s| s.nearest_frames(&times).0).collect();
    // Picked frames that got a pose, per lens: frame index, image name, mask name and the
    // openings whose jaws the mask covers.
    let mut written: Vec<Vec<Picked>> = vec![Vec::new(); lenses.len()];
    let mut unposed = 0usize;
    // Per rig: its wrist's trajectory and its reference lens (the front where exported).
    let rig_wrists: Vec<_> = scene
        .rigs
        .iter()
        .map(|rig| ep.wrists.iter().find(|w| Some(w.side) == rig.side))
        .collect();
    for k in 0..times.len() {
        let group = first_group + k;
        for (r, wrist) in rig_wrists.iter().enumerate() {
            if scene.rigs[r].side.is_none() {
                // The head camera: posed by the head's track.
                for &li in &scene.rigs[r].lenses.clone() {
                    let frame = picks[li][k];
                    let t = streams[li].session_times[frame] + centre_delays[li];
                    let Some(cam) = ep.head.as_ref().and_then(|h| h.at(t)) else {
                        unposed += 1;
                        continue;
                    };
                    let image = Shot {
                        ep: &ep.name,
                        lens: li,
                        view: &lenses[li].view,
                        frame,
                        scene_from_cam: cam.scene_from_cam,
                        points2d: Vec::new(),
                        test: group.is_multiple_of(SPLIT_EVERY),
                        openings: Vec::new(),
                    };
                    let id = add_image(scene, &mut written, image);
                    scene.frames.push(RigFrame {
                        id: scene.frames.len() as u32 + 1,
                        rig: r,
                        ref_from_scene: cam.scene_from_cam.inverse(),
                        images: vec![id],
                    });
                }
                continue;
            }
            let Some(wrist) = wrist else {
                continue;
            };
            let rig_lenses = &scene.rigs[r].lenses;
            let ref_lens = &lenses[rig_lenses[0]];
            // Each lens's frame, at the front-lens time of its centre row's exposure.
            let mut shots: Vec<(usize, usize, f64)> = rig_lenses
                .iter()
                .map(|&li| {
                    let frame = picks[li][k];
                    let t = streams[li].session_times[frame]
                        + lenses[li].shift_from_front_s
                        + centre_delays[li];
                    (li, frame, t)
                })
                .collect();
            shots.sort_by(|a, b| a.2.total_cmp(&b.2));
            // The rig frame being filled: its index, time, the front camera's pose and the
            // gripper opening (with its confidence).
            let mut current: Option<(usize, f64, Pose, Option<f64>, f64)> = None;
            for (li, frame, t) in shots {
                let (frame_index, scene_from_front, opening, confidence) = match current {
                    Some((f, t0, pose, o, c)) if (t - t0).abs() <= RIG_SYNC_TOL_S => {
                        (f, pose, o, c)
                    }
                    _ => {
                        let Some(sample) = wrist
                            .sample(t)
                            .filter(|s| s.support != SupportClass::ImuOnly)
                        else {
                            unposed += 1;
                            current = None;
                            continue;
                        };
                        let pose = sample.scene_from_front_cam;
                        scene.frames.push(RigFrame {
                            id: scene.frames.len() as u32 + 1,
                            rig: r,
                            ref_from_scene: (pose * ref_lens.front_from_lens).inverse(),
                            images: Vec::new(),
                        });
                        let f = scene.frames.len() - 1;
                        let (o, c) = (sample.opening, sample.opening_confidence);
                        current = Some((f, t, pose, o, c));
                        (f, pose, o, c)
                    }
                };
                let lens = &lenses[li];
                let image = Shot {
                    ep: &ep.name,
                    lens: li,
                    view: &lens.view,
                    frame,
                    scene_from_cam: scene_from_front * lens.front_from_lens,
                    points2d: observations(maps, &ep.name, &lens.view, frame),
                    test: group.is_multiple_of(SPLIT_EVERY),
                    openings: lens
                        .tool
                        .as_ref()
                        .map_or_else(Vec::new, |tool| mask_openings(tool, opening, confidence)),
                };
                let id = add_image(scene, &mut written, image);
                scene.frames[frame_index].images.push(id);
            }
        }
    }
    if written.iter().all(Vec::is_empty) {
        return Err(export_err(format!(
            "episode {}: none of its {} sampled time(s) has a visually supported pose on any \
             wrist (see quality.json); leave the episode out with --episodes",
            ep.name,
            times.len()
        )));
    }
    // Frames are in time order (the picks of increasing times).
    let images = &scene.images;
    let colour_sums = &mut scene.colour_sums;
    for (li, frames) in written.iter().enumerate() {
        let indices: Vec<usize> = frames.iter().map(|f| f.frame).collect();
        let lens = &lenses[li];
        let view = lens.view.key();
        super::video::for_each_pick(
            &streams[li].source,
            &indices,
            |m| export_err(format!("episode {}: view {view}: {m}", ep.name)),
            |k, frame| {
                let rgb = frame.to_rgb();
                // The map points this image observes take their colour from it.
                for (px, id) in &images[frames[k].image].points2d {
                    let x = (px[0] - PIXEL_CENTRE_OFFSET).round();
                    let y = (px[1] - PIXEL_CENTRE_OFFSET).round();
                    if x < 0.0 || y < 0.0 || x >= frame.width as f64 || y >= frame.height as f64 {
                        continue;
                    }
                    let at = (y as usize * frame.width + x as usize) * 3;
                    let e = colour_sums.entry(*id).or_insert(([0; 3], 0));
                    for c in 0..3 {
                        e.0[c] += u64::from(rgb[at + c]);
                    }
                    e.1 += 1;
                }
                let mut png = Vec::new();
                image::codecs::png::PngEncoder::new(&mut png)
                    .write_image(
                        &rgb,
                        frame.width as u32,
                        frame.height as u32,
                        image::ExtendedColorType::Rgb8,
                    )
                    .map_err(|e| export_err(format!("cannot encode {}: {e}", frames[k].name)))?;
                write_atomic(&dir.join(IMAGES_DIR).join(&frames[k].name), &png)?;
                let solids: Vec<_> = frames[k]
                    .openings
                    .iter()
                    .flat_map(|&o| lens.tool.as_ref().map(|t| t.solids(o)).unwrap_or_default())
                    .collect();
                let mask = lens.masker.mask(&solids);
                let mut png = Vec::new();
                image::codecs::png::PngEncoder::new(&mut png)
                    .write_image(
                        mask.as_raw(),
                        mask.width(),
                        mask.height(),
                        image::ExtendedColorType::L8,
                    )
                    .map_err(|e| {
                        export_err(format!("cannot encode {}: {e}", frames[k].mask_name))
                    })?;
                write_atomic(&dir.join(IMAGES_DIR).join(&frames[k].mask_name), &png)?;
                Ok(())
            },
        )?;
    }
    Ok((times.len(), unposed))
}

/// A posed frame about to become an exported image.
struct Shot<'a> {
    ep: &'a str,
    lens: usize,
    view: &'a View,
    frame: usize,
    scene_from_cam: Pose,
    points2d: Vec<([f64; 2], u64)>,
    test: bool,
    /// The gripper openings whose jaws its mask covers (none on the head camera).
    openings: Vec<f64>,
}

/// Add an image to the scene and to its lens's frames to write; returns its id.
fn add_image(scene: &mut Scene, written: &mut [Vec<Picked>], shot: Shot<'_>) -> u32 {
    let id = scene.images.len() as u32 + 1;
    let stem = format!(
        "{}/{}_{}/{:06}",
        shot.ep, shot.view.camera, shot.view.lens, shot.frame
    );
    let name = format!("{stem}.png");
    let mask_name = format!("{stem}{MASK_SUFFIX}");
    scene.images.push(SceneImage {
        id,
        lens: shot.lens,
        name: name.clone(),
        scene_from_cam: shot.scene_from_cam,
        mask_name: mask_name.clone(),
        points2d: shot.points2d,
        test: shot.test,
    });
    written[shot.lens].push(Picked {
        frame: shot.frame,
        image: scene.images.len() - 1,
        name,
        mask_name,
        openings: shot.openings,
    });
    id
}

/// A sampled frame that got a pose.
#[derive(Clone)]
struct Picked {
    /// Index in the lens's stream.
    frame: usize,
    /// Index in the scene's images.
    image: usize,
    /// Image name under `images/`.
    name: String,
    /// Mask name under `images/`.
    mask_name: String,
    /// Openings whose jaws the mask covers.
    openings: Vec<f64>,
}

/// The map features seen in a frame that is one of a map's keyframes: `(pixel in COLMAP's
/// convention, point id)`.
fn observations(
    maps: &[SceneMap],
    episode: &str,
    view: &View,
    frame: usize,
) -> Vec<([f64; 2], u64)> {
    let mut out = Vec::new();
    for m in maps {
        if m.map.episode != episode || m.map.camera_name != view.camera || m.map.lens != view.lens {
            continue;
        }
        for kf in m.map.keyframes.iter().filter(|k| k.frame as usize == frame) {
            for f in &kf.features {
                if let Some(l) = f.landmark
                    && (l as usize) < m.scene_points.len()
                {
                    out.push((
                        [
                            f.pixel[0] + PIXEL_CENTRE_OFFSET,
                            f.pixel[1] + PIXEL_CENTRE_OFFSET,
                        ],
                        m.first_id + u64::from(l),
                    ));
                }
            }
        }
    }
    out
}

/// Every map landmark as a point, with its tracks in the exported images and its mean
/// reprojection error through the lens models (0 without observations).
fn fill_points(scene: &mut Scene, maps: &[SceneMap]) {
    for m in maps {
        for (i, p) in m.scene_points.iter().enumerate() {
            scene.points.insert(
                m.first_id + i as u64,
                ScenePoint {
                    xyz: *p,
                    track: Vec::new(),
                    error_px: 0.0,
                    rgb: scene
                        .colour_sums
                        .get(&(m.first_id + i as u64))
                        .map_or([POINT_GREY; 3], |(sum, n)| {
                            sum.map(|c| (c as f64 / *n as f64).round() as u8)
                        }),
                },
            );
        }
    }
    let mut sums: BTreeMap<u64, (f64, usize)> = BTreeMap::new();
    for img in &scene.images {
        let cam = &scene.lenses[img.lens].model;
        let cam_from_scene = img.scene_from_cam.inverse();
        for (k, (px, id)) in img.points2d.iter().enumerate() {
            let Some(point) = scene.points.get_mut(id) else {
                continue;
            };
            point.track.push((img.id, k));
            if let Some(proj) =
                cam.project(&(cam_from_scene * nalgebra::Point3::from(point.xyz)).coords)
            {
                let observed =
                    Point2::new(px[0] - PIXEL_CENTRE_OFFSET, px[1] - PIXEL_CENTRE_OFFSET);
                let e = sums.entry(*id).or_insert((0.0, 0));
                e.0 += (proj - observed).norm();
                e.1 += 1;
            }
        }
    }
    for (id, (sum, n)) in sums {
        if let Some(p) = scene.points.get_mut(&id) {
            p.error_px = sum / n as f64;
        }
    }
}

/// `qw qx qy qz tx ty tz` of a pose, as COLMAP writes them.
fn colmap_pose(p: &Pose) -> String {
    let q = p.rotation.coords;
    let t = p.translation.vector;
    format!("{} {} {} {} {} {} {}", q.w, q.x, q.y, q.z, t.x, t.y, t.z)
}

fn write_text(path: &Path, text: &str) -> Result<()> {
    write_atomic(path, text.as_bytes()).map_err(BackendError::from)
}

fn write_colmap(scene: &Scene, dir: &Path) -> Result<()> {
    let dir = &dir.join(COLMAP_MODEL_DIR);
    let mut cameras = String::from(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, \
         PARAMS[]\n",
    );
    let _ = writeln!(cameras, "# Number of cameras: {}", scene.lenses.len());
    for l in &scene.lenses {
        let params: Vec<String> = l.fisheye.params.iter().map(f64::to_string).collect();
        let _ = writeln!(
            cameras,
            "{} OPENCV_FISHEYE {} {} {}",
            l.camera_id,
            l.fisheye.width,
            l.fisheye.height,
            params.join(" ")
        );
    }
    write_text(&dir.join("cameras.txt"), &cameras)?;

    let mut rigs = String::from(
        "# Rig calib list with one line of data per calib:\n#   RIG_ID, NUM_SENSORS, \
         REF_SENSOR_TYPE, REF_SENSOR_ID, SENSORS[] as (SENSOR_TYPE, SENSOR_ID, HAS_POSE, [QW, QX, \
         QY, QZ, TX, TY, TZ])\n",
    );
    let _ = writeln!(rigs, "# Number of rigs: {}", scene.rigs.len());
    for (r, rig) in scene.rigs.iter().enumerate() {
        let reference = &scene.lenses[rig.lenses[0]];
        let _ = write!(
            rigs,
            "{} {} CAMERA {}",
            r + 1,
            rig.lenses.len(),
            reference.camera_id
        );
        for &li in &rig.lenses[1..] {
            let l = &scene.lenses[li];
            // sensor_from_rig = lens_from_front · front_from_ref.
            let sensor_from_rig = l.front_from_lens.inverse() * reference.front_from_lens;
            let _ = write!(
                rigs,
                " CAMERA {} 1 {}",
                l.camera_id,
                colmap_pose(&sensor_from_rig)
            );
        }
        rigs.push('\n');
    }
    write_text(&dir.join("rigs.txt"), &rigs)?;

    let mut frames = String::from(
        "# Frame list with one line of data per frame:\n#   FRAME_ID, RIG_ID, RIG_FROM_WORLD[QW, \
         QX, QY, QZ, TX, TY, TZ], NUM_DATA_IDS, DATA_IDS[] as (SENSOR_TYPE, SENSOR_ID, DATA_ID)\n",
    );
    let _ = writeln!(frames, "# Number of frames: {}", scene.frames.len());
    for f in &scene.frames {
        let _ = write!(
            frames,
            "{} {} {} {}",
            f.id,
            f.rig + 1,
            colmap_pose(&f.ref_from_scene),
            f.images.len()
        );
        for &id in &f.images {
            let lens = &scene.lenses[scene.images[id as usize - 1].lens];
            let _ = write!(frames, " CAMERA {} {id}", lens.camera_id);
        }
        frames.push('\n');
    }
    write_text(&dir.join("frames.txt"), &frames)?;

    let mut images = String::from(
        "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, \
         CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n",
    );
    let _ = writeln!(images, "# Number of images: {}", scene.images.len());
    for img in &scene.images {
        let lens = &scene.lenses[img.lens];
        let _ = writeln!(
            images,
            "{} {} {} {}",
            img.id,
            colmap_pose(&img.scene_from_cam.inverse()),
            lens.camera_id,
            img.name
        );
        let obs: Vec<String> = img
            .points2d
            .iter()
            .map(|(p, id)| format!("{} {} {id}", p[0], p[1]))
            .collect();
        images.push_str(&obs.join(" "));
        images.push('\n');
    }
    write_text(&dir.join("images.txt"), &images)?;

    let mut points = String::from(
        "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, \
         ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n",
    );
    let _ = writeln!(points, "# Number of points: {}", scene.points.len());
    for (id, p) in &scene.points {
        let _ = write!(
            points,
            "{id} {} {} {} {} {} {} {}",
            p.xyz.x, p.xyz.y, p.xyz.z, p.rgb[0], p.rgb[1], p.rgb[2], p.error_px
        );
        for (image, k) in &p.track {
            let _ = write!(points, " {image} {k}");
        }
        points.push('\n');
    }
    write_text(&dir.join("points3D.txt"), &points)
}

/// nerfstudio's camera axes (OpenGL: x right, y up, z backwards) from KIWI's (x right, y down,
/// z forward): `cv_from_gl`.
fn cv_from_gl() -> nalgebra::Matrix4<f64> {
    nalgebra::Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, -1.0, -1.0, 1.0))
}

/// A camera-to-world pose as nerfstudio's `transform_matrix` (OpenGL camera axes; the world is
/// KIWI's scene frame, z up).
pub fn nerfstudio_matrix(scene_from_cam: &Pose) -> nalgebra::Matrix4<f64> {
    scene_from_cam.to_homogeneous() * cv_from_gl()
}

fn write_nerfstudio(scene: &Scene, dir: &Path) -> Result<()> {
    use serde_json::{Value, json};
    let intrinsics = |l: &Lens| {
        let p = l.fisheye.params;
        json!({
            "fl_x": p[0], "fl_y": p[1], "cx": p[2], "cy": p[3],
            "k1": p[4], "k2": p[5], "k3": p[6], "k4": p[7],
            "w": l.fisheye.width, "h": l.fisheye.height,
        })
    };
    let shared = scene
        .lenses
        .windows(2)
        .all(|w| w[0].fisheye == w[1].fisheye);
    let mut frames = Vec::new();
    for img in &scene.images {
        let m = nerfstudio_matrix(&img.scene_from_cam);
        let rows: Vec<Vec<f64>> = (0..4)
            .map(|r| (0..4).map(|c| m[(r, c)]).collect())
            .collect();
        let mut frame = json!({
            "file_path": format!("{IMAGES_DIR}/{}", img.name),
            "mask_path": format!("{IMAGES_DIR}/{}", img.mask_name),
            "transform_matrix": rows,
            "colmap_im_id": img.id,
        });
        if !shared
            && let (Value::Object(f), Value::Object(i)) =
                (&mut frame, intrinsics(&scene.lenses[img.lens]))
        {
            f.extend(i);
        }
        frames.push(frame);
    }
    let names = |test: bool| -> Vec<String> {
        scene
            .images
            .iter()
            .filter(|i| i.test == test)
            .map(|i| format!("{IMAGES_DIR}/{}", i.name))
            .collect()
    };
    let mut doc = json!({
        "camera_model": "OPENCV_FISHEYE",
        "frames": frames,
        "ply_file_path": PLY_FILE,
        "train_filenames": names(false),
        "val_filenames": names(true),
        "test_filenames": names(true),
    });
    if shared
        && let (Value::Object(d), Some(l)) = (&mut doc, scene.lenses.first())
        && let Value::Object(i) = intrinsics(l)
    {
        d.extend(i);
    }
    let text = serde_json::to_vec_pretty(&doc)
        .map_err(|e| export_err(format!("cannot encode transforms.json: {e}")))?;
    write_atomic(&dir.join("transforms.json"), &text)?;
    let mut ply = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty \
         float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        scene.points.len()
    );
    for p in scene.points.values() {
        let _ = writeln!(
            ply,
            "{} {} {} {} {} {}",
            p.xyz.x, p.xyz.y, p.xyz.z, p.rgb[0], p.rgb[1], p.rgb[2]
        );
    }
    write_text(&dir.join(PLY_FILE), &ply)
}

fn write_split(scene: &Scene, dir: &Path) -> Result<()> {
    for (file, test) in [(TEST_LIST, true), (TRAIN_LIST, false)] {
        let mut text = String::new();
        for img in scene.images.iter().filter(|i| i.test == test) {
            let _ = writeln!(text, "{}", img.name);
        }
        write_text(&dir.join(file), &text)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kb4_moves_only_the_principal_point() {
        let cam = Camera::Kb4(
            Kb4::new(
                960,
                960,
                [300.0, 301.0, 480.0, 479.0, 0.02, -0.003, 5e-4, -5e-5],
            )
            .unwrap(),
        );
        let f = opencv_fisheye(&cam, 3.3).unwrap();
        assert_eq!(
            f.params,
            [300.0, 301.0, 480.5, 479.5, 0.02, -0.003, 5e-4, -5e-5]
        );
        assert!(f.refit.is_none());
    }

    #[test]
    fn double_sphere_refits_within_a_tenth_of_a_pixel() {
        let ds = DoubleSphere::new(960, 960, [350.0, 350.0, 480.0, 480.0, -0.2, 0.6]).unwrap();
        let max_theta = 195f64.to_radians() / 2.0;
        let f = opencv_fisheye(&Camera::DoubleSphere(ds.clone()), 2.0 * max_theta).unwrap();
        assert!(f.refit.is_some());
        // The written camera, back in KIWI's pixel convention, against the lens at azimuths
        // and angles the fit did not sample.
        let mut p = f.params;
        p[2] -= PIXEL_CENTRE_OFFSET;
        p[3] -= PIXEL_CENTRE_OFFSET;
        let kb4 = Kb4::new(960, 960, p).unwrap();
        for i in 0..40 {
            let theta = max_theta * (i as f64 + 0.37) / 40.0;
            for phi in [0.3, std::f64::consts::FRAC_PI_4, 2.0] {
                let d = bearing_from_angles(theta, phi);
                let (a, b) = (ds.project(&d).unwrap(), kb4.project(&d).unwrap());
                assert!(
                    (a - b).norm() < MAX_REFIT_ERROR_PX,
                    "θ {theta}, φ {phi}: {}",
                    (a - b).norm()
                );
            }
        }
    }

    #[test]
    fn a_lens_kb4_cannot_follow_is_refused() {
        // A strongly negative ξ over a 200° field bends the radius beyond a 9th-order polynomial.
        let ds = DoubleSphere::new(960, 960, [300.0, 300.0, 480.0, 480.0, -0.6, 0.5]).unwrap();
        let err = opencv_fisheye(&Camera::DoubleSphere(ds), 200f64.to_radians()).unwrap_err();
        assert!(err.contains("cannot be written as OPENCV_FISHEYE"), "{err}");
    }
}
