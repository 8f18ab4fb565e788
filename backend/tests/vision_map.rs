//! The visual map file: exact round trip, validation errors that name the field, and refusal to
//! localize another lens model, resolution or lens (another calibration of the same model is
//! served: the rear map is shared by both wrists' units); maps of older schemas (descriptors of
//! the raw fisheye image) are refused with "rebuild the map".
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use kiwi_backend::vision::features::Descriptor;
use kiwi_backend::vision::map::{
    FeaturePatch, MAP_SCHEMA_VERSION, MapFeature, MapKeyframe, MapLandmark, MapPose, VisualMap,
};
use kiwi_core::camera::{Camera, CameraModel, DoubleSphere, Kb4};
use kiwi_core::geometry::{Pose, so3_exp};
use nalgebra::{Translation3, Vector3};

fn kb4() -> Camera {
    Camera::Kb4(
        Kb4::new(
            960,
            960,
            [283.1, 283.4, 479.2, 480.7, 0.021, -0.0031, 0.0005, -0.00005],
        )
        .unwrap(),
    )
}

fn sample_map() -> VisualMap {
    let mut map = VisualMap::new("left", "rear", "ep000", &kb4());
    map.landmarks = (0..3u32)
        .map(|i| MapLandmark {
            position: [0.1 * f64::from(i), -1.0 / 3.0, 2.0 + f64::from(i)],
            descriptor: Descriptor([u64::MAX, 0x0123_4567_89ab_cdef, u64::from(i), 1 << 63]),
        })
        .collect();
    for k in 0..2u32 {
        let pose = Pose::from_parts(
            Translation3::new(0.1 * f64::from(k), 0.0, 0.0),
            so3_exp(&Vector3::new(0.0, 0.01 * f64::from(k), 0.3)),
        );
        map.keyframes.push(MapKeyframe {
            frame: 10 * k,
            t: 0.1 * f64::from(k),
            cam_from_map: MapPose::from_pose(&pose),
            features: vec![
                MapFeature {
                    pixel: [100.25, 200.5],
                    bearing: Vector3::new(0.3, -0.2, -0.1).normalize().into(),
                    descriptor: Descriptor([1, 2, 3, 4]),
                    landmark: Some(k),
                    octave: Some(2),
                    patch: Some(FeaturePatch(std::array::from_fn(|i| {
                        (i * 7 + k as usize) as u8
                    }))),
                },
                MapFeature {
                    pixel: [10.0, 20.0],
                    bearing: [0.0, 0.0, 1.0],
                    descriptor: Descriptor([5, 6, 7, 8]),
                    landmark: None,
                    octave: None,
                    patch: None,
                },
            ],
        });
    }
    map.train_vocabulary();
    map
}

#[test]
fn map_round_trips_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rear.kmap");
    let map = sample_map();
    map.save(&path).unwrap();
    let back = VisualMap::load(&path).unwrap();
    assert_eq!(map, back);
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.contains("\"format\":\"kiwi-visual-map\""));
    assert!(text.contains("ffffffffffffffff"));
    // The pose survives the file.
    let p = back.keyframes[1].cam_from_map.to_pose().unwrap();
    assert!((p.translation.vector.x - 0.1).abs() < 1e-15);
    // The camera is rebuilt and accepted for the same lens.
    back.check_query_lens("rear", &back.camera.camera().unwrap())
        .unwrap();
}

#[test]
fn map_refuses_other_lenses_with_a_clear_error() {
    let map = sample_map();
    let ds = Camera::DoubleSphere(
        DoubleSphere::new(960, 960, [300.0, 300.0, 479.5, 479.5, -0.2, 0.6]).unwrap(),
    );
    let err = map.check_query_lens("rear", &ds).unwrap_err().to_string();
    assert!(
        err.contains("double_sphere") && err.contains("kiwi map --lens rear"),
        "{err}"
    );
    let err = map
        .check_query_lens("front", &kb4())
        .unwrap_err()
        .to_string();
    assert!(err.contains("lens `front`"), "{err}");
    let small =
        Camera::Kb4(Kb4::new(480, 480, [141.0, 141.0, 239.5, 239.5, 0.02, 0.0, 0.0, 0.0]).unwrap());
    let err = map
        .check_query_lens("rear", &small)
        .unwrap_err()
        .to_string();
    assert!(err.contains("480x480"), "{err}");
    let mut other = kb4();
    let mut p = other.params().to_vec();
    p[0] += 1.0;
    other.set_params(&p).unwrap();
    // Another unit's calibration of the same model and size is served.
    map.check_query_lens("rear", &other).unwrap();
}

#[test]
fn maps_without_a_vocabulary_learn_one_and_older_schemas_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("old.kmap");
    let mut map = sample_map();
    map.vocabulary = None;
    // Keyframe 1 sees other things than keyframe 0.
    map.keyframes[1].features[0].descriptor = Descriptor([u64::MAX; 4]);
    map.keyframes[1].features[1].descriptor = Descriptor([u64::MAX, 0, u64::MAX, 0]);
    // A map assembled in memory without a vocabulary learns one for place recognition.
    let mut back = map.clone();
    let db = back.keyframe_database();
    assert!(back.vocabulary.is_some());
    let query = back.vocabulary.as_ref().unwrap().bow(&[
        Descriptor([u64::MAX; 4]),
        Descriptor([u64::MAX, 0, u64::MAX, 0]),
    ]);
    let hits = db.query(&query, 5);
    assert_eq!(hits[0].1, 1, "{hits:?}");
    assert!(hits[0].0 > 0.99, "{hits:?}");
    // A file without its vocabulary is refused, naming the field.
    map.schema_version = MAP_SCHEMA_VERSION;
    std::fs::write(&path, serde_json::to_string(&map).unwrap()).unwrap();
    let err = VisualMap::load(&path).unwrap_err().to_string();
    assert!(err.contains("vocabulary"), "{err}");
    // Schemas 1 and 2 hold descriptors of the raw fisheye image: refused with the fix.
    for old in [1, 2] {
        let mut m = sample_map();
        m.schema_version = old;
        std::fs::write(&path, serde_json::to_string(&m).unwrap()).unwrap();
        let err = VisualMap::load(&path).unwrap_err().to_string();
        assert!(
            err.contains("schema_version") && err.contains("rebuild the map"),
            "{err}"
        );
    }
}

#[test]
fn invalid_map_files_name_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.kmap");
    let mut map = sample_map();
    map.keyframes[0].features[0].landmark = Some(99);
    let err = map.save(&path).unwrap_err().to_string();
    assert!(err.contains("keyframes[0].features[0].landmark"), "{err}");
    assert!(!path.exists(), "nothing is written for an invalid map");

    let mut map = sample_map();
    map.schema_version = MAP_SCHEMA_VERSION + 1;
    let text = serde_json::to_string(&map).unwrap();
    std::fs::write(&path, text).unwrap();
    let err = VisualMap::load(&path).unwrap_err().to_string();
    assert!(
        err.contains("schema_version") && err.contains("bad.kmap"),
        "{err}"
    );

    std::fs::write(&path, "{\"format\": 3}").unwrap();
    let err = VisualMap::load(&path).unwrap_err().to_string();
    assert!(err.contains("not a valid KIWI visual map"), "{err}");

    let mut map = sample_map();
    map.keyframes[1].t = 0.0;
    let err = map.save(&path).unwrap_err().to_string();
    assert!(err.contains("keyframes[1].t"), "{err}");
}
