//! The visual map file (`.kmap`): versioned, self-describing JSON, loadable without the images.
//!
//! A map holds what localization needs: the lens it was built from (camera model, parameters,
//! resolution), keyframes with their poses and features (pixel, bearing, ORB descriptor, the
//! landmark each feature observes), and landmarks with positions and a representative
//! descriptor. Poses are `cam_from_map`; the map frame and scale are arbitrary (metric recovery
//! is a later stage). A map refuses to serve a lens of another name, model or resolution, with
//! an error that says which map to build instead.
//!
//! Descriptors are written as 64 hexadecimal digits (256 bits, little-endian words) so that no
//! JSON reader loses precision.

use std::path::Path;

use nalgebra::{Matrix2, Point2, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use kiwi_core::camera::{Camera, CameraModel, CameraModelKind, DoubleSphere, Kb4};
use kiwi_core::geometry::Pose;

use crate::error::{BackendError, Result};
use crate::vision::features::{
    Descriptor, GrayImage, Keypoint, TangentPatch, direction_basis, patch_step,
};
use crate::vision::place::{KeyframeDatabase, Vocabulary};
use crate::vision::quality::MapQuality;

/// The `format` tag of a map file.
pub const MAP_FORMAT: &str = "kiwi-visual-map";
/// The schema version this build writes (3: descriptors computed on rectified patches around
/// each keypoint's bearing, `OrbOptions::rectified`; 2 added the place-recognition vocabulary).
pub const MAP_SCHEMA_VERSION: u32 = 3;
/// The oldest schema this build reads: older maps hold descriptors of the raw fisheye image,
/// which do not match this build's, and must be rebuilt.
pub const MAP_SCHEMA_OLDEST: u32 = 3;
/// Largest deviation of a unit vector's norm from one in a valid file.
const UNIT_TOLERANCE: f64 = 1e-6;
/// Side (px) of a keyframe feature's stored patch: 11 × 11 samples at the feature's angular
/// scale, enough texture for a correlation to stand out from its neighbourhood, small enough to
/// stay on one surface.
pub const PATCH_SIDE: usize = 11;

/// The image around a keyframe feature's landmark as that keyframe saw it: [`PATCH_SIDE`]²
/// luma samples, row-major, around the keyframe's ray to the landmark, in the tangent basis
/// [`crate::vision::features::direction_basis`] of that ray, at the feature's angular scale
/// (its pyramid level). Serialized as hexadecimal digits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FeaturePatch(pub [u8; PATCH_SIDE * PATCH_SIDE]);

/// Lower-case hexadecimal digits of `bytes`, in order.
fn to_hex(bytes: &[u8]) -> String {
    const DIGITS: &[u8; 16] = b"0123456789abcdef";
    let mut text = String::with_capacity(2 * bytes.len());
    for &b in bytes {
        text.push(char::from(DIGITS[usize::from(b >> 4)]));
        text.push(char::from(DIGITS[usize::from(b & 0x0f)]));
    }
    text
}

/// The `N` bytes that `2 N` hexadecimal digits spell, or what is wrong with them.
fn from_hex<const N: usize>(text: &str) -> std::result::Result<[u8; N], String> {
    if text.len() != 2 * N || !text.is_ascii() {
        return Err(format!(
            "expected {} hexadecimal digits, found {} characters",
            2 * N,
            text.len()
        ));
    }
    let mut bytes = [0u8; N];
    for (k, b) in bytes.iter_mut().enumerate() {
        *b = u8::from_str_radix(&text[2 * k..2 * k + 2], 16)
            .map_err(|e| format!("bad hexadecimal digits: {e}"))?;
    }
    Ok(bytes)
}

impl Serialize for FeaturePatch {
    fn serialize<S: Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(&to_hex(&self.0))
    }
}

impl<'de> Deserialize<'de> for FeaturePatch {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        from_hex(&text).map(Self).map_err(serde::de::Error::custom)
    }
}

impl Serialize for Descriptor {
    fn serialize<S: Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        let bytes: Vec<u8> = self.0.iter().flat_map(|w| w.to_be_bytes()).collect();
        s.serialize_str(&to_hex(&bytes))
    }
}

impl<'de> Deserialize<'de> for Descriptor {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        let bytes: [u8; 32] = from_hex(&text).map_err(serde::de::Error::custom)?;
        let mut words = [0u64; 4];
        for (w, chunk) in words.iter_mut().zip(bytes.chunks_exact(8)) {
            let mut word = [0u8; 8];
            word.copy_from_slice(chunk);
            *w = u64::from_be_bytes(word);
        }
        Ok(Self(words))
    }
}

/// The lens a map was built from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapCamera {
    /// Camera model.
    pub model: CameraModelKind,
    /// Image size `[width, height]` (px).
    pub resolution: [u32; 2],
    /// Parameters in the model's documented order.
    pub params: Vec<f64>,
}

impl MapCamera {
    /// Describe a camera.
    pub fn from_camera(camera: &dyn CameraModel) -> Self {
        let (w, h) = camera.resolution();
        Self {
            model: camera.kind(),
            resolution: [w, h],
            params: camera.params().to_vec(),
        }
    }

    /// The camera model (validated).
    pub fn camera(&self) -> Result<Camera> {
        let [w, h] = self.resolution;
        let bad = |n: usize| BackendError::Vision {
            context: "map camera".into(),
            message: format!(
                "expected {n} parameters for model {}, found {}",
                self.model,
                self.params.len()
            ),
        };
        Ok(match self.model {
            CameraModelKind::Kb4 => {
                let p: [f64; 8] = self.params.as_slice().try_into().map_err(|_| bad(8))?;
                Camera::Kb4(Kb4::new(w, h, p)?)
            }
            CameraModelKind::DoubleSphere => {
                let p: [f64; 6] = self.params.as_slice().try_into().map_err(|_| bad(6))?;
                Camera::DoubleSphere(DoubleSphere::new(w, h, p)?)
            }
        })
    }
}

/// A rigid transform as stored: unit quaternion `[x, y, z, w]` and translation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MapPose {
    /// Rotation quaternion `[x, y, z, w]`.
    pub rotation_xyzw: [f64; 4],
    /// Translation (map units).
    pub translation: [f64; 3],
}

impl MapPose {
    /// From a pose.
    pub fn from_pose(p: &Pose) -> Self {
        let q = p.rotation.quaternion();
        let t = p.translation.vector;
        Self {
            rotation_xyzw: [q.i, q.j, q.k, q.w],
            translation: [t.x, t.y, t.z],
        }
    }

    /// To a pose; `None` unless finite with a unit quaternion.
    pub fn to_pose(&self) -> Option<Pose> {
        let [x, y, z, w] = self.rotation_xyzw;
        let q = Quaternion::new(w, x, y, z);
        let all_finite = self
            .rotation_xyzw
            .iter()
            .chain(&self.translation)
            .all(|v| v.is_finite());
        if !all_finite || (q.norm() - 1.0).abs() > UNIT_TOLERANCE {
            return None;
        }
        Some(Pose::from_parts(
            Translation3::from(Vector3::from(self.translation)),
            UnitQuaternion::from_quaternion(q),
        ))
    }
}

/// A feature of a keyframe.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MapFeature {
    /// Pixel `[x, y]`.
    pub pixel: [f64; 2],
    /// Unit bearing in the keyframe's camera frame.
    pub bearing: [f64; 3],
    /// ORB descriptor.
    pub descriptor: Descriptor,
    /// Index of the landmark it observes, if any.
    pub landmark: Option<u32>,
    /// Pyramid level of the keypoint its descriptor was taken at (`None`: the descriptor was
    /// taken in another frame of the feature's track).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub octave: Option<u8>,
    /// The keyframe's image around the landmark (see [`FeaturePatch`]), for features with a
    /// landmark and a known level.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub patch: Option<FeaturePatch>,
}

impl MapFeature {
    /// The feature as a keypoint at pyramid level `octave` (no detector response).
    pub fn keypoint(&self, octave: u8) -> Keypoint {
        Keypoint {
            pixel: Point2::new(self.pixel[0], self.pixel[1]),
            bearing: Vector3::from(self.bearing),
            octave: i32::from(octave),
            response: 0.0,
        }
    }
}

/// A keyframe.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapKeyframe {
    /// Frame index in the mapping episode's `frames.csv`.
    pub frame: u32,
    /// Frame time (s, camera clock).
    pub t: f64,
    /// Map coordinates to camera coordinates.
    pub cam_from_map: MapPose,
    /// Features.
    pub features: Vec<MapFeature>,
}

/// A landmark.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MapLandmark {
    /// Position in the map frame.
    pub position: [f64; 3],
    /// Representative descriptor (the medoid of its observations).
    pub descriptor: Descriptor,
}

/// A frozen visual map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VisualMap {
    /// Always [`MAP_FORMAT`].
    pub format: String,
    /// Schema version ([`MAP_SCHEMA_VERSION`]).
    pub schema_version: u32,
    /// The program that wrote it (`kiwi <version>`).
    pub created_by: String,
    /// Camera folder name the map was built from (`left`, `right`, `head`).
    pub camera_name: String,
    /// Lens name (`front`, `rear`, `main`).
    pub lens: String,
    /// Mapping episode name.
    pub episode: String,
    /// The lens's calibration.
    pub camera: MapCamera,
    /// Keyframes in time order.
    pub keyframes: Vec<MapKeyframe>,
    /// Landmarks (indexed by [`MapFeature::landmark`]).
    pub landmarks: Vec<MapLandmark>,
    /// Place-recognition vocabulary learned from the keyframes' descriptors (required; a map
    /// built in memory without one learns it when its keyframe database is first built).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vocabulary: Option<Vocabulary>,
    /// The mapper's own consistency check and verdict (`vision::quality`); absent in a map
    /// that was not checked (assembled in memory), which is served as trustworthy.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quality: Option<MapQuality>,
}

fn map_err(path: &Path, message: String) -> BackendError {
    BackendError::Input {
        path: path.to_path_buf(),
        message,
    }
}

fn finite(v: &[f64]) -> bool {
    v.iter().all(|x| x.is_finite())
}

fn unit(v: &[f64; 3]) -> bool {
    finite(v) && (Vector3::from(*v).norm() - 1.0).abs() <= UNIT_TOLERANCE
}

impl VisualMap {
    /// Store, for every keyframe feature with a landmark and a known pyramid level, the
    /// keyframe's image around its ray to the landmark ([`FeaturePatch`]) at the feature's
    /// angular scale (`scale_factor` per level); `image_of(k)` gives keyframe `k`'s image.
    /// Features whose patch leaves the field of view keep none.
    pub fn sample_patches(
        &mut self,
        camera: &dyn CameraModel,
        scale_factor: f64,
        mut image_of: impl FnMut(usize) -> Result<GrayImage>,
    ) -> Result<()> {
        let positions: Vec<Vector3<f64>> = self
            .landmarks
            .iter()
            .map(|l| Vector3::from(l.position))
            .collect();
        for (k, kf) in self.keyframes.iter_mut().enumerate() {
            let Some(pose) = kf.cam_from_map.to_pose() else {
                continue;
            };
            if !kf
                .features
                .iter()
                .any(|f| f.landmark.is_some() && f.octave.is_some())
            {
                continue;
            }
            let image = image_of(k)?;
            for f in &mut kf.features {
                let (Some(l), Some(octave)) = (f.landmark, f.octave) else {
                    continue;
                };
                let Some(x) = positions.get(l as usize) else {
                    continue;
                };
                let pc = (pose * Point3::from(*x)).coords;
                let n = pc.norm();
                if n.is_nan() || n <= 0.0 {
                    continue;
                }
                let direction = pc / n;
                let Some(step) = patch_step(camera, &f.keypoint(octave), scale_factor) else {
                    continue;
                };
                let (e1, e2) = direction_basis(&direction);
                let patch = TangentPatch {
                    direction,
                    e1,
                    e2,
                    step,
                    shape: Matrix2::identity(),
                };
                if let Some(values) = patch.sample(&image, camera, PATCH_SIDE) {
                    let mut bytes = [0u8; PATCH_SIDE * PATCH_SIDE];
                    for (b, v) in bytes.iter_mut().zip(values) {
                        *b = v.round().clamp(0.0, 255.0) as u8;
                    }
                    f.patch = Some(FeaturePatch(bytes));
                }
            }
        }
        Ok(())
    }

    /// An empty map for a lens.
    pub fn new(camera_name: &str, lens: &str, episode: &str, camera: &dyn CameraModel) -> Self {
        Self {
            format: MAP_FORMAT.into(),
            schema_version: MAP_SCHEMA_VERSION,
            created_by: format!("kiwi {}", env!("CARGO_PKG_VERSION")),
            camera_name: camera_name.into(),
            lens: lens.into(),
            episode: episode.into(),
            camera: MapCamera::from_camera(camera),
            keyframes: Vec::new(),
            landmarks: Vec::new(),
            vocabulary: None,
            quality: None,
        }
    }

    /// Learn the place-recognition vocabulary from the keyframes' descriptors (replaces any).
    pub fn train_vocabulary(&mut self) {
        let docs: Vec<Vec<Descriptor>> = self
            .keyframes
            .iter()
            .map(|k| k.features.iter().map(|f| f.descriptor).collect())
            .collect();
        self.vocabulary = Some(Vocabulary::train(&docs));
    }

    /// The keyframe database for place recognition (learns a vocabulary first if the map has
    /// none: a map assembled in memory).
    pub fn keyframe_database(&mut self) -> KeyframeDatabase {
        if self.vocabulary.is_none() {
            self.train_vocabulary();
        }
        let docs: Vec<Vec<Descriptor>> = self
            .keyframes
            .iter()
            .map(|k| k.features.iter().map(|f| f.descriptor).collect())
            .collect();
        match &self.vocabulary {
            Some(v) => KeyframeDatabase::build(v, &docs),
            None => KeyframeDatabase::default(),
        }
    }

    /// Check every field; `path` names the file in errors.
    pub fn validate(&self, path: &Path) -> Result<()> {
        if self.format != MAP_FORMAT {
            return Err(map_err(
                path,
                format!(
                    "field `format`: expected \"{MAP_FORMAT}\", found \"{}\"; this is not a KIWI \
                     visual map",
                    self.format
                ),
            ));
        }
        if self.schema_version < MAP_SCHEMA_OLDEST {
            return Err(map_err(
                path,
                format!(
                    "field `schema_version`: {} is a map whose descriptors were computed on the \
                     raw fisheye image; this kiwi describes features on rectified patches \
                     (schema {MAP_SCHEMA_VERSION}) and cannot match them: rebuild the map with \
                     `kiwi map`",
                    self.schema_version
                ),
            ));
        }
        if self.schema_version > MAP_SCHEMA_VERSION {
            return Err(map_err(
                path,
                format!(
                    "field `schema_version`: this kiwi reads version {MAP_SCHEMA_VERSION}, found \
                     {} (written by a newer kiwi); rebuild the map with this kiwi (`kiwi map`) \
                     or update kiwi",
                    self.schema_version
                ),
            ));
        }
        if let Some(v) = &self.vocabulary {
            v.check()
                .map_err(|e| map_err(path, format!("field `vocabulary`: {e}")))?;
        } else {
            return Err(map_err(
                path,
                "field `vocabulary`: missing; rebuild the map with `kiwi map`".into(),
            ));
        }
        self.camera
            .camera()
            .map_err(|e| map_err(path, format!("field `camera`: {e}")))?;
        if let Some(q) = &self.quality {
            let figures = [
                q.direction_disagreement.unwrap_or(0.0),
                q.reversed_coverage,
                q.landmarks_per_keyframe,
                q.shared_landmarks_p10,
                q.keyframes_per_frame,
            ];
            if !finite(&figures) || figures.iter().any(|&x| x < 0.0) {
                return Err(map_err(
                    path,
                    "field `quality`: expected finite, non-negative figures; rebuild the map \
                     with `kiwi map`"
                        .into(),
                ));
            }
            if q.reversed_coverage > 1.0
                || q.trustworthy
                    != crate::vision::quality::verdict(
                        q.reversed_coverage,
                        q.direction_disagreement,
                    )
                    .is_empty()
            {
                return Err(map_err(
                    path,
                    "field `quality`: the verdict `trustworthy` does not follow from the figures \
                     beside it; rebuild the map with `kiwi map`"
                        .into(),
                ));
            }
            if !q.trustworthy && q.reason.is_empty() {
                return Err(map_err(
                    path,
                    "field `quality.reason`: a map that is not trustworthy must say why; \
                     rebuild the map with `kiwi map`"
                        .into(),
                ));
            }
        }
        let n_land = self.landmarks.len();
        for (i, l) in self.landmarks.iter().enumerate() {
            if !finite(&l.position) {
                return Err(map_err(
                    path,
                    format!("field `landmarks[{i}].position`: expected finite numbers"),
                ));
            }
        }
        let mut last_t = f64::NEG_INFINITY;
        for (k, kf) in self.keyframes.iter().enumerate() {
            if kf.cam_from_map.to_pose().is_none() {
                return Err(map_err(
                    path,
                    format!(
                        "field `keyframes[{k}].cam_from_map`: expected a finite pose with a unit \
                         quaternion"
                    ),
                ));
            }
            if !kf.t.is_finite() || kf.t <= last_t {
                return Err(map_err(
                    path,
                    format!(
                        "field `keyframes[{k}].t`: expected finite, strictly increasing times, \
                         found {} after {last_t}",
                        kf.t
                    ),
                ));
            }
            last_t = kf.t;
            for (f, feat) in kf.features.iter().enumerate() {
                let where_ = format!("keyframes[{k}].features[{f}]");
                if !finite(&feat.pixel) || !unit(&feat.bearing) {
                    return Err(map_err(
                        path,
                        format!("field `{where_}`: expected a finite pixel and a unit bearing"),
                    ));
                }
                if let Some(l) = feat.landmark
                    && l as usize >= n_land
                {
                    return Err(map_err(
                        path,
                        format!(
                            "field `{where_}.landmark`: {l} but the map has {n_land} landmarks"
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Write atomically as JSON.
    pub fn save(&self, path: &Path) -> Result<()> {
        self.validate(path)?;
        let bytes = serde_json::to_vec(self).map_err(|e| map_err(path, e.to_string()))?;
        kiwi_core::io::write_atomic(path, &bytes)?;
        Ok(())
    }

    /// Read and validate a map file.
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|source| kiwi_core::CoreError::Io {
            action: "reading",
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_bytes(&bytes, path)
    }

    /// Parse and validate map file content; `path` names it in errors.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Self> {
        let rebuild = "rebuild it with `kiwi map` (or give the .kmap file `kiwi map` wrote)";
        let Ok(text) = std::str::from_utf8(bytes) else {
            return Err(map_err(
                path,
                format!(
                    "expected a KIWI visual map (JSON text written by `kiwi map`), found binary \
                     data; {rebuild}"
                ),
            ));
        };
        if !text.trim_start().starts_with('{') {
            let start: String = text.trim_start().chars().take(20).collect();
            return Err(map_err(
                path,
                format!(
                    "expected a KIWI visual map (a JSON object written by `kiwi map`), found text \
                     starting `{start}`; {rebuild}"
                ),
            ));
        }
        let map: Self = serde_json::from_str(text)
            .map_err(|e| map_err(path, format!("not a valid KIWI visual map: {e}; {rebuild}")))?;
        map.validate(path)?;
        Ok(map)
    }

    /// Refuse to localize a lens this map was not built for: another lens name (front/rear/
    /// main) or camera model, or another resolution (ORB descriptors are not scale invariant
    /// enough across image sizes). Another calibration of the same model is accepted: the query
    /// unprojects with its own calibration, which is how the rear map serves both wrists' units.
    pub fn check_query_lens(&self, lens: &str, camera: &dyn CameraModel) -> Result<()> {
        let query = MapCamera::from_camera(camera);
        let problem = if lens != self.lens {
            Some(format!(
                "lens `{lens}` but the map was built from lens `{}`",
                self.lens
            ))
        } else if query.model != self.camera.model {
            Some(format!(
                "a {} lens but the map was built with a {} model",
                query.model, self.camera.model
            ))
        } else if query.resolution != self.camera.resolution {
            Some(format!(
                "{}x{} images but the map was built from {}x{}",
                query.resolution[0],
                query.resolution[1],
                self.camera.resolution[0],
                self.camera.resolution[1]
            ))
        } else {
            None
        };
        match problem {
            None => Ok(()),
            Some(p) => Err(BackendError::Vision {
                context: format!(
                    "map of {}/{} ({})",
                    self.camera_name, self.lens, self.episode
                ),
                message: format!(
                    "cannot localize {p}; build a map for this lens with `kiwi map --lens {lens}`"
                ),
            }),
        }
    }
}

/// Largest distance (px) between a keyframe's ORB keypoint and a tracked point for the keypoint
/// to inherit the track's landmark (tracks start on ORB keypoints; KLT drifts sub-pixel).
pub const ASSOCIATION_RADIUS_PX: f64 = 2.0;

impl VisualMap {
    /// Export a reconstruction: every keyframe keeps all its ORB features (`keyframe_features`,
    /// one entry per keyframe, from the keyframe's image); a feature within
    /// [`ASSOCIATION_RADIUS_PX`] of a tracked observation of a mapped track observes that
    /// landmark. Landmarks that no feature describes are left out (they could never be matched);
    /// a landmark's descriptor is the medoid of its features' descriptors.
    pub fn from_reconstruction(
        recon: &crate::vision::mapping::Reconstruction,
        keyframe_features: &[crate::vision::features::FrameFeatures],
        camera_name: &str,
        lens: &str,
        episode: &str,
        camera: &dyn CameraModel,
    ) -> Result<Self> {
        Self::from_reconstruction_described(
            recon,
            keyframe_features,
            &std::collections::BTreeMap::new(),
            camera_name,
            lens,
            episode,
            camera,
        )
    }

    /// [`VisualMap::from_reconstruction`] (which also learns the place-recognition vocabulary),
    /// and in addition every keyframe observation of a
    /// mapped track that no keyframe keypoint lands on becomes a feature of that keyframe with
    /// the track's descriptor from `track_descriptors` (taken where the front-end detected the
    /// track), so that far more landmarks are described and matchable.
    #[allow(clippy::too_many_arguments)]
    pub fn from_reconstruction_described(
        recon: &crate::vision::mapping::Reconstruction,
        keyframe_features: &[crate::vision::features::FrameFeatures],
        track_descriptors: &std::collections::BTreeMap<u64, Descriptor>,
        camera_name: &str,
        lens: &str,
        episode: &str,
        camera: &dyn CameraModel,
    ) -> Result<Self> {
        if keyframe_features.len() != recon.keyframes.len() {
            return Err(BackendError::Vision {
                context: "map export".into(),
                message: format!(
                    "expected features for each of the {} keyframes, found {}",
                    recon.keyframes.len(),
                    keyframe_features.len()
                ),
            });
        }
        let mut map = Self::new(camera_name, lens, episode, camera);
        // Track id → descriptors of the features that observe it.
        let mut described: std::collections::BTreeMap<u64, Vec<Descriptor>> =
            std::collections::BTreeMap::new();
        let mut feature_track: Vec<Vec<Option<u64>>> = Vec::with_capacity(recon.keyframes.len());
        let mut born: std::collections::BTreeMap<u64, Descriptor> =
            std::collections::BTreeMap::new();
        let mut extras: Vec<Vec<(crate::vision::mapping::TrackObservation, Descriptor)>> =
            Vec::with_capacity(recon.keyframes.len());
        let r2 = ASSOCIATION_RADIUS_PX * ASSOCIATION_RADIUS_PX;
        for (kf, feats) in recon.keyframes.iter().zip(keyframe_features) {
            let mapped: Vec<&crate::vision::mapping::TrackObservation> = kf
                .observations
                .iter()
                .filter(|o| recon.landmarks.contains_key(&o.track))
                .collect();
            let mut used = std::collections::BTreeSet::new();
            let mut tracks = Vec::with_capacity(feats.keypoints.len());
            for (kp, d) in feats.keypoints.iter().zip(&feats.descriptors) {
                let mut best: Option<(f64, u64)> = None;
                for o in &mapped {
                    let d2 = (o.pixel - kp.pixel).norm_squared();
                    if d2 <= r2 && best.is_none_or(|b| d2 < b.0) {
                        best = Some((d2, o.track));
                    }
                }
                // One feature per track and keyframe: the strongest (features come sorted).
                let track = best.map(|b| b.1).filter(|t| used.insert(*t));
                if let Some(t) = track {
                    described.entry(t).or_default().push(*d);
                }
                tracks.push(track);
            }
            let mut more = Vec::new();
            for o in &mapped {
                if used.contains(&o.track) {
                    continue;
                }
                if let Some(d) = track_descriptors.get(&o.track) {
                    more.push((**o, *d));
                }
            }
            feature_track.push(tracks);
            extras.push(more);
        }
        // Tracks no keyframe keypoint describes take their detection descriptor (keypoint
        // descriptors, when there are any, stay the landmark's: they are the ones a query's ORB
        // reproduces best).
        for (o, d) in extras.iter().flatten() {
            if !described.contains_key(&o.track) {
                born.entry(o.track).or_insert(*d);
            }
        }
        for (t, d) in &born {
            described.insert(*t, vec![*d]);
        }
        let mut index: std::collections::BTreeMap<u64, u32> = std::collections::BTreeMap::new();
        for (track, descs) in &described {
            let Some(p) = recon.landmarks.get(track) else {
                continue;
            };
            index.insert(*track, map.landmarks.len() as u32);
            map.landmarks.push(MapLandmark {
                position: [p.x, p.y, p.z],
                descriptor: medoid(descs),
            });
        }
        for (((kf, feats), tracks), more) in recon
            .keyframes
            .iter()
            .zip(keyframe_features)
            .zip(feature_track)
            .zip(extras)
        {
            let mut features: Vec<MapFeature> = feats
                .keypoints
                .iter()
                .zip(&feats.descriptors)
                .zip(tracks)
                .map(|((kp, d), t)| MapFeature {
                    pixel: [kp.pixel.x, kp.pixel.y],
                    bearing: [kp.bearing.x, kp.bearing.y, kp.bearing.z],
                    descriptor: *d,
                    landmark: t.and_then(|t| index.get(&t).copied()),
                    octave: u8::try_from(kp.octave).ok(),
                    patch: None,
                })
                .collect();
            features.extend(more.iter().map(|(o, d)| MapFeature {
                pixel: [o.pixel.x, o.pixel.y],
                bearing: [o.bearing.x, o.bearing.y, o.bearing.z],
                descriptor: *d,
                landmark: index.get(&o.track).copied(),
                octave: None,
                patch: None,
            }));
            map.keyframes.push(MapKeyframe {
                frame: kf.frame,
                t: kf.t,
                cam_from_map: MapPose::from_pose(&kf.cam_from_world),
                features,
            });
        }
        map.train_vocabulary();
        Ok(map)
    }
}

/// The descriptor with the smallest summed Hamming distance to the others (first on ties).
fn medoid(descs: &[Descriptor]) -> Descriptor {
    let mut best = (u32::MAX, Descriptor([0; 4]));
    for a in descs {
        let total: u32 = descs.iter().map(|b| a.distance(b)).sum();
        if total < best.0 {
            best = (total, *a);
        }
    }
    best.1
}
