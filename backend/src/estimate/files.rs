//! File formats and the driver of `kiwi fuse`.
//!
//! - `frames.csv`: header whose first column is `t`; one node per row (camera clock, s).
//! - `obs.csv`: header `t,source,px,py,pz,qx,qy,qz,qw`; `source` ∈ {front, rear}; the pose is
//!   the body observation `scene_from_imu` on the IMU clock.
//! - `traj.csv` (output): header `t,px,py,pz,qx,qy,qz,qw,sigma_p,sigma_r,support`, one row per
//!   node on the frame clock: `scene_from_front_cam` (with a calibration) or `scene_from_imu`
//!   (without), marginal position/rotation sigmas (m, rad; square roots of the traces of the
//!   3×3 marginal blocks) and the supporting factors ([`Support::label`]).

use std::path::{Path, PathBuf};

use kiwi_core::artifact::UnitCalibration;
use kiwi_core::geometry::Pose;
use kiwi_core::imu::ImuSeries;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use super::fusion::{FusionConfig, PoseObservation, Source, Support, fuse};
use super::preint::ImuParams;
use crate::error::{BackendError, Result};

/// Header of `obs.csv`.
pub const OBSERVATIONS_HEADER: &str = "t,source,px,py,pz,qx,qy,qz,qw";
/// Header of `traj.csv`.
pub const TRAJECTORY_HEADER: &str = "t,px,py,pz,qx,qy,qz,qw,sigma_p,sigma_r,support";
/// Standard gravity used for fusion in a z-up scene (m/s²).
pub const GRAVITY_M_S2: f64 = 9.81;
/// Quaternions further than this from unit norm are rejected rather than normalised.
const QUATERNION_NORM_TOLERANCE: f64 = 1e-3;

fn input(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

fn read(path: &Path) -> Result<String> {
    std::fs::read_to_string(path)
        .map_err(|e| input(path, format!("cannot read: {e}; check the path")))
}

/// Node timestamps from the first column (`t`) of `frames.csv`.
pub fn read_frames(path: &Path) -> Result<Vec<f64>> {
    let text = read(path)?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let header = lines
        .next()
        .map(|(_, l)| l.trim().to_string())
        .unwrap_or_default();
    if header.split(',').next().map(str::trim) != Some("t") {
        return Err(input(
            path,
            format!("expected a header whose first column is `t`, found `{header}`"),
        ));
    }
    let mut times = Vec::new();
    for (i, line) in lines {
        let field = line.split(',').next().unwrap_or("").trim();
        let t: f64 = field.parse().map_err(|_| {
            input(
                path,
                format!(
                    "line {}: expected a time in seconds, found `{field}`",
                    i + 1
                ),
            )
        })?;
        if !t.is_finite() {
            return Err(input(path, format!("line {}: time is not finite", i + 1)));
        }
        if let Some(&prev) = times.last()
            && t <= prev
        {
            return Err(input(
                path,
                format!(
                    "line {}: time {t} does not increase after {prev}; frames must be sorted \
                     and unique",
                    i + 1
                ),
            ));
        }
        times.push(t);
    }
    if times.len() < 2 {
        return Err(input(
            path,
            format!("expected at least 2 frames, found {}", times.len()),
        ));
    }
    Ok(times)
}

/// Pose observations from `obs.csv`.
pub fn read_observations(path: &Path) -> Result<Vec<PoseObservation>> {
    let text = read(path)?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let header = lines
        .next()
        .map(|(_, l)| l.trim().replace(' ', ""))
        .unwrap_or_default();
    if header != OBSERVATIONS_HEADER {
        return Err(input(
            path,
            format!("expected the header `{OBSERVATIONS_HEADER}`, found `{header}`"),
        ));
    }
    let mut out = Vec::new();
    for (i, line) in lines {
        let row = i + 1;
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        if fields.len() != 9 {
            return Err(input(
                path,
                format!("line {row}: expected 9 fields, found {}", fields.len()),
            ));
        }
        let source = match fields[1] {
            "front" => Source::Front,
            "rear" => Source::Rear,
            other => {
                return Err(input(
                    path,
                    format!("line {row}: source must be `front` or `rear`, found `{other}`"),
                ));
            }
        };
        let mut v = [0.0; 8];
        for (k, idx) in [0usize, 2, 3, 4, 5, 6, 7, 8].iter().enumerate() {
            v[k] = fields[*idx]
                .parse()
                .ok()
                .filter(|x: &f64| x.is_finite())
                .ok_or_else(|| {
                    let name = OBSERVATIONS_HEADER.split(',').nth(*idx).unwrap_or("?");
                    input(
                        path,
                        format!(
                            "line {row}: `{name}` is not a finite number: `{}`",
                            fields[*idx]
                        ),
                    )
                })?;
        }
        let q = Quaternion::new(v[7], v[4], v[5], v[6]);
        if (q.norm() - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
            return Err(input(
                path,
                format!(
                    "line {row}: quaternion (qx,qy,qz,qw) has norm {:.6}, expected 1; write unit \
                     quaternions",
                    q.norm()
                ),
            ));
        }
        out.push(PoseObservation {
            t: v[0],
            source,
            scene_from_imu: Isometry3::from_parts(
                Translation3::new(v[1], v[2], v[3]),
                UnitQuaternion::from_quaternion(q),
            ),
        });
    }
    if out.is_empty() {
        return Err(input(path, "no observations".into()));
    }
    Ok(out)
}

/// Columns of a localizer's `poses.csv` that `kiwi metric` and `kiwi place` read (by name; other
/// columns such as `inliers` and `reason` are ignored).
const LOCALIZATION_COLUMNS: [&str; 9] = ["t", "status", "px", "py", "pz", "qx", "qy", "qz", "qw"];

/// One row of a localizer's `poses.csv` (`map_from_cam` on the camera clock).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Localization {
    /// Frame time on the camera clock (s).
    pub t: f64,
    /// `tracked` or `relocalized` (a pose was accepted); `lost` rows are `false`.
    pub valid: bool,
    /// `map_from_cam` (identity for lost rows).
    pub map_from_cam: Pose,
}

/// Read `poses.csv` (`t,status,px,py,pz,qx,qy,qz,qw,...`, status ∈ {tracked, relocalized,
/// lost}); lost rows may leave the pose empty.
pub fn read_localizations(path: &Path) -> Result<Vec<Localization>> {
    let text = read(path)?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let header: Vec<String> = lines
        .next()
        .map(|(_, l)| l.split(',').map(|c| c.trim().to_string()).collect())
        .unwrap_or_default();
    let mut index = [0usize; 9];
    for (slot, name) in index.iter_mut().zip(LOCALIZATION_COLUMNS) {
        *slot = header.iter().position(|c| c == name).ok_or_else(|| {
            input(
                path,
                format!(
                    "missing column `{name}`: expected a localizer poses.csv with columns {} \
                     (found `{}`)",
                    LOCALIZATION_COLUMNS.join(","),
                    header.join(",")
                ),
            )
        })?;
    }
    let mut out: Vec<Localization> = Vec::new();
    for (i, line) in lines {
        let row = i + 1;
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        let field = |k: usize| fields.get(index[k]).copied().unwrap_or("");
        let number = |k: usize| -> Result<f64> {
            field(k)
                .parse()
                .ok()
                .filter(|x: &f64| x.is_finite())
                .ok_or_else(|| {
                    input(
                        path,
                        format!(
                            "line {row}: `{}` is not a finite number: `{}`",
                            LOCALIZATION_COLUMNS[k],
                            field(k)
                        ),
                    )
                })
        };
        let t = number(0)?;
        if let Some(prev) = out.last()
            && t <= prev.t
        {
            return Err(input(
                path,
                format!("line {row}: time {t} does not increase after {}", prev.t),
            ));
        }
        let valid = match field(1) {
            "tracked" | "relocalized" => true,
            "lost" => false,
            other => {
                return Err(input(
                    path,
                    format!(
                        "line {row}: status must be tracked, relocalized or lost, found `{other}`"
                    ),
                ));
            }
        };
        let map_from_cam = if valid {
            let mut v = [0.0; 7];
            for (k, slot) in v.iter_mut().enumerate() {
                *slot = number(2 + k)?;
            }
            let q = Quaternion::new(v[6], v[3], v[4], v[5]);
            if (q.norm() - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
                return Err(input(
                    path,
                    format!(
                        "line {row}: quaternion (qx,qy,qz,qw) has norm {:.6}, expected 1",
                        q.norm()
                    ),
                ));
            }
            Isometry3::from_parts(
                Translation3::new(v[0], v[1], v[2]),
                UnitQuaternion::from_quaternion(q),
            )
        } else {
            Pose::identity()
        };
        out.push(Localization {
            t,
            valid,
            map_from_cam,
        });
    }
    if out.is_empty() {
        return Err(input(path, "no rows after the header".into()));
    }
    Ok(out)
}

/// One row of `traj.csv`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrajectoryRow {
    /// Frame time (s).
    pub t: f64,
    /// The output pose.
    pub pose: Pose,
    /// Position sigma (m).
    pub sigma_p: f64,
    /// Rotation sigma (rad).
    pub sigma_r: f64,
    /// Supporting factors.
    pub support: Support,
}

/// Write `traj.csv` atomically.
pub fn write_trajectory(path: &Path, rows: &[TrajectoryRow]) -> Result<()> {
    let mut s = String::with_capacity(rows.len() * 160);
    s.push_str(TRAJECTORY_HEADER);
    s.push('\n');
    for r in rows {
        let p = r.pose.translation.vector;
        let q = r.pose.rotation.coords;
        s.push_str(&format!(
            "{:.9},{:.9},{:.9},{:.9},{:.12},{:.12},{:.12},{:.12},{:.6e},{:.6e},{}\n",
            r.t,
            p.x,
            p.y,
            p.z,
            q.x,
            q.y,
            q.z,
            q.w,
            r.sigma_p,
            r.sigma_r,
            r.support.label()
        ));
    }
    kiwi_core::io::write_atomic(path, s.as_bytes())?;
    Ok(())
}

/// Inputs of `kiwi fuse`.
#[derive(Debug, Clone)]
pub struct FuseOptions {
    /// `imu.csv`.
    pub imu: PathBuf,
    /// `frames.csv`.
    pub frames: PathBuf,
    /// `obs.csv`.
    pub observations: PathBuf,
    /// Unit `calibration.json` (IMU noise, `cam_from_imu`, time shift).
    pub calibration: Option<PathBuf>,
    /// Lens whose frames are the nodes.
    pub lens: String,
    /// IMU noise densities `[gn, gw, an, aw]` (required without a calibration).
    pub imu_noise: Option<[f64; 4]>,
    /// Fusion settings.
    pub config: FusionConfig,
    /// Output `traj.csv`.
    pub out: PathBuf,
}

/// Summary printed by `kiwi fuse --json`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct FuseSummary {
    /// Nodes written.
    pub nodes: usize,
    /// Visual factors used.
    pub observations_used: usize,
    /// Visual factors downweighted by the Huber loss.
    pub outliers_downweighted: usize,
    /// Solver iterations.
    pub iterations: usize,
    /// Final cost.
    pub final_cost: f64,
    /// Wall time (s).
    pub seconds: f64,
}

/// What the estimators need of one lens of a unit artifact.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensImuCalibration {
    /// The lens's `cam_from_imu`.
    pub cam_from_imu: Pose,
    /// Kalibr time shift: `t_imu = t_cam + time_shift_s`.
    pub time_shift_s: f64,
    /// IMU noise densities `[gn, gw, an, aw]`, when the artifact has an `imu` block.
    pub imu_noise: Option<[f64; 4]>,
}

/// Load `lens`'s camera–IMU calibration and the IMU noise from a unit `calibration.json`.
pub fn load_lens_calibration(path: &Path, lens: &str) -> Result<LensImuCalibration> {
    let cal = UnitCalibration::load(path)?;
    let entry = cal.lens(lens).ok_or_else(|| {
        let names: Vec<&str> = cal.lenses.iter().map(|l| l.name.as_str()).collect();
        input(
            path,
            format!("no lens `{lens}`; the unit has {names:?}; pass --lens"),
        )
    })?;
    let cam_from_imu = entry.cam_from_imu().ok_or_else(|| {
        input(
            path,
            format!("lens `{lens}` has no cam_from_imu; run the camera-IMU calibration first"),
        )
    })?;
    Ok(LensImuCalibration {
        cam_from_imu,
        time_shift_s: entry.time_shift_s.unwrap_or(0.0),
        imu_noise: cal.imu.as_ref().map(|imu| {
            [
                imu.gyroscope_noise_density,
                imu.gyroscope_random_walk,
                imu.accelerometer_noise_density,
                imu.accelerometer_random_walk,
            ]
        }),
    })
}

/// IMU parameters from explicit densities, else the calibration's, else an error naming both.
pub fn imu_params(
    explicit: Option<[f64; 4]>,
    calibration: Option<(&Path, &LensImuCalibration)>,
) -> Result<ImuParams> {
    let noise = match (explicit, calibration) {
        (Some(n), _) => n,
        (None, Some((path, cal))) => cal.imu_noise.ok_or_else(|| {
            input(
                path,
                "no `imu` noise block; calibrate the IMU (kiwi-calib imu-noise) or pass \
                 --imu-noise"
                    .into(),
            )
        })?,
        (None, None) => {
            return Err(BackendError::Estimation(
                "without --calibration, give the IMU noise as --imu-noise GN,GW,AN,AW".into(),
            ));
        }
    };
    let [gn, gw, an, aw] = noise;
    Ok(ImuParams::from_densities(gn, gw, an, aw, GRAVITY_M_S2))
}

/// Run `kiwi fuse`.
pub fn run_fuse(opts: &FuseOptions) -> Result<FuseSummary> {
    let start = std::time::Instant::now();
    let lens_cal = opts
        .calibration
        .as_deref()
        .map(|path| load_lens_calibration(path, &opts.lens).map(|c| (path, c)))
        .transpose()?;
    let time_shift = lens_cal.as_ref().map_or(0.0, |(_, c)| c.time_shift_s);
    let cam_from_imu = lens_cal.as_ref().map(|(_, c)| c.cam_from_imu);
    let params = imu_params(opts.imu_noise, lens_cal.as_ref().map(|(p, c)| (*p, c)))?;
    let imu = ImuSeries::read_csv(&opts.imu)?;
    let frames = read_frames(&opts.frames)?;
    let observations = read_observations(&opts.observations)?;
    // Kalibr convention: t_imu = t_cam + time_shift_s.
    let node_times: Vec<f64> = frames.iter().map(|t| t + time_shift).collect();
    let result = fuse(
        imu.samples(),
        &params,
        &node_times,
        &observations,
        &opts.config,
    )?;
    let rows: Vec<TrajectoryRow> = result
        .nodes
        .iter()
        .zip(&frames)
        .map(|(n, &t)| {
            let (pose, sigma_p, sigma_r) =
                n.camera_pose(&cam_from_imu.unwrap_or_else(Pose::identity));
            TrajectoryRow {
                t,
                pose,
                sigma_p,
                sigma_r,
                support: n.support,
            }
        })
        .collect();
    write_trajectory(&opts.out, &rows)?;
    Ok(FuseSummary {
        nodes: rows.len(),
        observations_used: result.observations_used,
        outliers_downweighted: result.outliers_downweighted,
        iterations: result.iterations,
        final_cost: result.final_cost,
        seconds: start.elapsed().as_secs_f64(),
    })
}
