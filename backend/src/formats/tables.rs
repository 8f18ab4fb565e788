//! The CSV tables the estimation commands exchange.
//!
//! - `frames.csv`: header whose first column is `t`; one node per row (camera clock, s).
//! - `obs.csv`: header `t,source,px,py,pz,qx,qy,qz,qw`; `source` ∈ {front, rear}; the pose is
//!   the body observation `scene_from_imu` on the IMU clock.
//! - `traj.csv` (output): header `t,px,py,pz,qx,qy,qz,qw,sigma_p,sigma_r,support`, one row per
//!   node on the frame clock: `scene_from_front_cam` (with a calibration) or `scene_from_imu`
//!   (without), marginal position/rotation sigmas (m, rad; square roots of the traces of the
//!   3×3 marginal blocks) and the supporting factors ([`Support::label`]).

use std::path::Path;

use kiwi_core::geometry::Pose;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::error::{BackendError, Result};
use crate::fusion::{PoseObservation, Source, Support};

/// Header of `obs.csv`.
pub const OBSERVATIONS_HEADER: &str = "t,source,px,py,pz,qx,qy,qz,qw";
/// Header of `traj.csv`.
pub const TRAJECTORY_HEADER: &str = "t,px,py,pz,qx,qy,qz,qw,sigma_p,sigma_r,support";
/// Quaternions further than this from unit norm are rejected rather than normalised.
const QUATERNION_NORM_TOLERANCE: f64 = 1e-3;

/// The pose of a table row from its position and `(qx, qy, qz, qw)` quaternion, every value
/// finite and the quaternion of unit norm (within [`QUATERNION_NORM_TOLERANCE`]; it is not
/// normalised). The error says what is wrong; the caller adds the file and row.
pub(crate) fn pose_from_row(p: [f64; 3], q_xyzw: [f64; 4]) -> std::result::Result<Pose, String> {
    if !p.iter().chain(&q_xyzw).all(|v| v.is_finite()) {
        return Err(format!(
            "expected a finite position and quaternion, found {p:?} and {q_xyzw:?}"
        ));
    }
    let [x, y, z, w] = q_xyzw;
    let q = Quaternion::new(w, x, y, z);
    if (q.norm() - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
        return Err(format!(
            "quaternion (qx,qy,qz,qw) has norm {:.6}, expected 1; write unit quaternions",
            q.norm()
        ));
    }
    Ok(Isometry3::from_parts(
        Translation3::from(nalgebra::Vector3::from(p)),
        UnitQuaternion::from_quaternion(q),
    ))
}

fn input(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

fn read(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| {
        input(
            path,
            format!("cannot read: {}", kiwi_core::error::describe_io(&e)),
        )
    })
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
        let scene_from_imu = pose_from_row([v[1], v[2], v[3]], [v[4], v[5], v[6], v[7]])
            .map_err(|m| input(path, format!("line {row}: {m}")))?;
        out.push(PoseObservation {
            t: v[0],
            source,
            scene_from_imu,
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

/// One frame of a localizer's `poses.csv` as the quality record and the session report read it:
/// its time and, when it was lost, why.
#[derive(Debug, Clone, PartialEq)]
pub struct LensFrame {
    /// Frame time on the camera clock (s).
    pub t: f64,
    /// The reason the frame was lost (`None`: a pose was accepted); an empty reason reads
    /// `no reason given`.
    pub lost: Option<String>,
}

/// Read the time, status and reason of every row of a localizer's `poses.csv` (the reason is
/// the last column and may itself hold commas).
pub fn read_lens_frames(path: &Path) -> Result<Vec<LensFrame>> {
    let text = read(path)?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let header: Vec<&str> = lines
        .next()
        .map(|(_, l)| l.split(',').map(str::trim).collect())
        .unwrap_or_default();
    let column = |name: &str| header.iter().position(|c| *c == name);
    let (Some(t_col), Some(status), Some(reason)) =
        (column("t"), column("status"), column("reason"))
    else {
        return Err(input(
            path,
            format!(
                "expected a poses.csv with t, status and reason columns (found `{}`); re-run the \
                 localize stage",
                header.join(",")
            ),
        ));
    };
    let mut out = Vec::new();
    for (i, line) in lines {
        let fields: Vec<&str> = line.splitn(header.len(), ',').collect();
        let field = |k: usize| fields.get(k).map_or("", |f| f.trim());
        let t: f64 = field(t_col)
            .parse()
            .ok()
            .filter(|t: &f64| t.is_finite())
            .ok_or_else(|| {
                input(
                    path,
                    format!(
                        "line {}: time `{}` is not a finite number",
                        i + 1,
                        field(t_col)
                    ),
                )
            })?;
        let lost = (field(status) == "lost").then(|| {
            let why = field(reason);
            if why.is_empty() {
                "no reason given".to_string()
            } else {
                why.to_string()
            }
        });
        out.push(LensFrame { t, lost });
    }
    Ok(out)
}

/// Read `poses.csv` (`t,status,px,py,pz,qx,qy,qz,qw,...`, status ∈ {tracked, relocalized,
/// lost}); lost rows may leave the pose empty.
pub fn read_localizations(path: &Path) -> Result<Vec<Localization>> {
    parse_localizations(&read(path)?, path)
}

/// [`read_localizations`] on text; `path` names it in errors.
pub fn parse_localizations(text: &str, path: &Path) -> Result<Vec<Localization>> {
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
            pose_from_row([v[0], v[1], v[2]], [v[3], v[4], v[5], v[6]])
                .map_err(|m| input(path, format!("line {row}: {m}")))?
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

/// Write `obs.csv` atomically (the format [`read_observations`] reads).
pub fn write_observations(path: &Path, observations: &[PoseObservation]) -> Result<()> {
    let mut s = String::with_capacity(observations.len() * 140 + 64);
    s.push_str(OBSERVATIONS_HEADER);
    s.push('\n');
    for o in observations {
        let p = o.scene_from_imu.translation.vector;
        let q = o.scene_from_imu.rotation.coords;
        let source = match o.source {
            Source::Front => "front",
            Source::Rear => "rear",
        };
        s.push_str(&format!(
            "{:.9},{source},{:.9},{:.9},{:.9},{:.12},{:.12},{:.12},{:.12}\n",
            o.t, p.x, p.y, p.z, q.x, q.y, q.z, q.w
        ));
    }
    kiwi_core::io::write_atomic(path, s.as_bytes())?;
    Ok(())
}

/// Header of `fused.csv`: per front frame, the frame's camera-clock time, its IMU-clock time,
/// `scene_from_imu` (position, quaternion), velocity, biases, the 21 upper-triangle entries of
/// the pose's marginal 6×6 covariance (`[rot; trans]`, row-major), the final Huber weights of
/// the front and rear factors (empty when none) and whether the rear factor was interpolated.
pub const FUSED_HEADER: &str = "t_camera,t_imu,px,py,pz,qx,qy,qz,qw,vx,vy,vz,bax,bay,baz,bgx,bgy,bgz,\
cov00,cov01,cov02,cov03,cov04,cov05,cov11,cov12,cov13,cov14,cov15,cov22,cov23,cov24,cov25,\
cov33,cov34,cov35,cov44,cov45,cov55,front_weight,rear_weight,rear_interpolated";

/// One row of `fused.csv`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusedRow {
    /// Front frame time on the camera clock (s).
    pub t_camera: f64,
    /// The node: pose, velocity, biases, covariance, support.
    pub node: crate::fusion::FusedNode,
}

/// Write `fused.csv` atomically: one row per node, with the node's camera-clock frame time.
pub fn write_fused(
    path: &Path,
    camera_times: &[f64],
    nodes: &[crate::fusion::FusedNode],
) -> Result<()> {
    let mut s = String::with_capacity(nodes.len() * 520 + 512);
    s.push_str(FUSED_HEADER);
    s.push('\n');
    for (n, t_cam) in nodes.iter().zip(camera_times) {
        let p = n.scene_from_imu.translation.vector;
        let q = n.scene_from_imu.rotation.coords;
        let v = n.velocity;
        let (ba, bg) = (n.bias.acc, n.bias.gyro);
        s.push_str(&format!(
            "{t_cam:.9},{:.9},{:.9},{:.9},{:.9},{:.12},{:.12},{:.12},{:.12},{:.6},{:.6},{:.6},\
             {:.7},{:.7},{:.7},{:.8},{:.8},{:.8}",
            n.t,
            p.x,
            p.y,
            p.z,
            q.x,
            q.y,
            q.z,
            q.w,
            v.x,
            v.y,
            v.z,
            ba.x,
            ba.y,
            ba.z,
            bg.x,
            bg.y,
            bg.z
        ));
        for i in 0..6 {
            for j in i..6 {
                s.push_str(&format!(",{:.6e}", n.pose_cov[(i, j)]));
            }
        }
        let weight = |w: Option<f64>| w.map_or_else(String::new, |w| format!("{w:.4}"));
        s.push_str(&format!(
            ",{},{},{}\n",
            weight(n.support.front),
            weight(n.support.rear),
            u8::from(n.support.rear_interpolated)
        ));
    }
    kiwi_core::io::write_atomic(path, s.as_bytes())?;
    Ok(())
}

/// Read `fused.csv`.
pub fn read_fused(path: &Path) -> Result<Vec<FusedRow>> {
    let text = read(path)?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let header = lines.next().map(|(_, l)| l.trim()).unwrap_or_default();
    if header != FUSED_HEADER {
        return Err(input(
            path,
            "unexpected header: not a KIWI fused.csv of this version; re-run the fusion stage"
                .into(),
        ));
    }
    let columns = FUSED_HEADER.split(',').count();
    let mut out = Vec::new();
    for (i, line) in lines {
        let row = i + 1;
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != columns {
            return Err(input(
                path,
                format!("line {row}: expected {columns} fields, found {}", f.len()),
            ));
        }
        let num = |k: usize| -> Result<f64> {
            f[k].trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| {
                    input(
                        path,
                        format!(
                            "line {row}: column {} is not a finite number: `{}`",
                            k + 1,
                            f[k]
                        ),
                    )
                })
        };
        let opt = |k: usize| -> Result<Option<f64>> {
            if f[k].trim().is_empty() {
                Ok(None)
            } else {
                num(k).map(Some)
            }
        };
        let scene_from_imu = pose_from_row(
            [num(2)?, num(3)?, num(4)?],
            [num(5)?, num(6)?, num(7)?, num(8)?],
        )
        .map_err(|m| input(path, format!("line {row}: {m}")))?;
        let mut cov = nalgebra::Matrix6::zeros();
        let mut k = 18;
        for a in 0..6 {
            for b in a..6 {
                let v = num(k)?;
                cov[(a, b)] = v;
                cov[(b, a)] = v;
                k += 1;
            }
        }
        out.push(FusedRow {
            t_camera: num(0)?,
            node: crate::fusion::FusedNode {
                t: num(1)?,
                scene_from_imu,
                velocity: nalgebra::Vector3::new(num(9)?, num(10)?, num(11)?),
                bias: crate::fusion::preint::ImuBias {
                    acc: nalgebra::Vector3::new(num(12)?, num(13)?, num(14)?),
                    gyro: nalgebra::Vector3::new(num(15)?, num(16)?, num(17)?),
                },
                pose_cov: cov,
                support: Support {
                    front: opt(39)?,
                    rear: opt(40)?,
                    rear_interpolated: f[41].trim() == "1",
                },
            },
        });
    }
    if out.is_empty() {
        return Err(input(path, "no rows after the header".into()));
    }
    Ok(out)
}
