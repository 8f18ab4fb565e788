//! LeRobot v3.0 datasets: `meta/info.json`, `meta/stats.json`, `meta/tasks.parquet`,
//! `meta/episodes/chunk-000/file-000.parquet`, one `data/chunk-CCC/file-FFF.parquet` and one
//! `videos/<key>/chunk-CCC/file-FFF.mp4` per view for each episode (file index = episode
//! index, a thousand files per chunk, every video starting at timestamp 0).
//!
//! `meta/stats.json` and each episode's `stats/<feature>/<stat>` columns hold `min`, `max`,
//! `mean`, `std` and `count` of every column, and per colour channel of every view (pixel
//! values scaled to 0..1, on a sample of the frames as LeRobot samples them; see
//! [`crate::export::stats`]), so that policies normalizing their inputs train as they would
//! on a dataset LeRobot wrote.
//!
//! Rows sit on a fixed-rate grid of the session timeline; row `k` of an episode has
//! `timestamp = k / fps` (from the episode's first row) and video frame `k` is presented at
//! exactly that time. Each wrist's tool tip is resampled from its fused trajectory; the video
//! frame of a row is the lens frame captured nearest the row's session time (the distance is
//! reported). Columns (`names` in `info.json` name every element):
//!
//! - `observation.state`, `action`: per wrist (left, then right) tool tip `x y z` (m) and
//!   quaternion `qx qy qz qw` of `scene_from_tip` (hemisphere kept continuous), and the gripper
//!   opening (rad for the chopstick, m for the parallel jaw, 0 for a bare hand); `action` is
//!   the state of the next row (the last row repeats its state).
//! - `kiwi.t_session` (float64): the row's session time (s).
//! - `kiwi.support` (int64 per wrist): 0 front, 1 rear, 2 rear-interpolated, 3 IMU only (the
//!   weaker of the two frames around the row).
//! - `kiwi.tip_sigma` (float32, per wrist position m and rotation rad).
//! - `kiwi.gripper_confidence` (float32 per wrist, 0 when the opening was not measured and the
//!   state holds the nearest measured value).
//! - `observation.images.<camera>_<lens>`: the views, H.264 mp4.

use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::path::Path;

use kiwi_core::layout::ToolKind;

use crate::error::Result;
use crate::export::parquet::Table;
use crate::export::stats::{ImageStats, Stats, Summary, image_sample_rows};
use crate::export::video::{KEYFRAME_INTERVAL, PIX_FMT, VIDEO_CODEC, encode_frames};
use crate::export::{
    ExportOptions, ExportReport, SessionExport, ViewStream, WristSample, choose_rate, create_dir,
    episode_grid, resolve_views, source_rates, support_code,
};

/// The format version LeRobot checks.
pub const CODEBASE_VERSION: &str = "v3.0";
/// Files per chunk folder (LeRobot's default).
pub const CHUNKS_SIZE: usize = 1000;
/// LeRobot's default file-size limits (MB), recorded in `info.json`.
const DATA_FILES_SIZE_MB: u32 = 100;
const VIDEO_FILES_SIZE_MB: u32 = 500;
/// `robot_type` in `info.json`.
pub const ROBOT_TYPE: &str = "kiwi_handheld_bimanual";
/// Values per wrist in `observation.state` and `action`.
pub const STATE_PER_WRIST: usize = 8;

/// The `names` of `observation.state` and `action` for the wrists given.
pub fn state_names(wrists: &[&str]) -> Vec<String> {
    let mut names = Vec::new();
    for w in wrists {
        for n in [
            "tip_x", "tip_y", "tip_z", "tip_qx", "tip_qy", "tip_qz", "tip_qw",
        ] {
            names.push(format!("{w}_{n}"));
        }
        names.push(format!("{w}_gripper"));
    }
    names
}

fn data_path(chunk: usize, file: usize) -> String {
    format!("data/chunk-{chunk:03}/file-{file:03}.parquet")
}

fn video_path(key: &str, chunk: usize, file: usize) -> String {
    format!("videos/{key}/chunk-{chunk:03}/file-{file:03}.mp4")
}

/// One episode's rows, ready for the data file.
#[derive(Default)]
struct Rows {
    timestamp: Vec<f32>,
    t_session: Vec<f64>,
    state: Vec<f32>,
    action: Vec<f32>,
    support: Vec<i64>,
    sigma: Vec<f32>,
    confidence: Vec<f32>,
}

/// The state vector of one wrist at a row (`previous_q` keeps quaternion signs continuous;
/// `last_opening` holds the opening where it was not measured).
fn wrist_state(
    s: &WristSample,
    tool: ToolKind,
    previous_q: &mut Option<[f64; 4]>,
    last_opening: &mut Option<f64>,
) -> [f64; STATE_PER_WRIST] {
    let p = s.scene_from_tip.translation.vector;
    let q = crate::export::continuous_quaternion(&s.scene_from_tip.rotation, *previous_q);
    *previous_q = Some(q);
    if s.opening.is_some() {
        *last_opening = s.opening;
    }
    let opening = match tool {
        ToolKind::BareHand => 0.0,
        _ => last_opening.unwrap_or(0.0),
    };
    [p.x, p.y, p.z, q[0], q[1], q[2], q[3], opening]
}

/// Write the dataset of `exp` into `dir`.
pub fn write(exp: &SessionExport, options: &ExportOptions, dir: &Path) -> Result<ExportReport> {
    let views = resolve_views(exp, options.views.as_deref())?;
    let wrist_names: Vec<&str> = exp.session.wrists.keys().map(|s| s.camera_name()).collect();
    let nw = wrist_names.len();
    let width = nw * STATE_PER_WRIST;
    let mut report = ExportReport::default();
    let mut tasks: Vec<String> = Vec::new();
    let mut stats_all: BTreeMap<String, Stats> = BTreeMap::new();
    let mut image_stats: BTreeMap<String, ImageStats> = BTreeMap::new();
    let mut episodes_meta: Vec<EpisodeMeta> = Vec::new();
    let mut video_info: BTreeMap<String, (usize, usize)> = BTreeMap::new();
    let mut fps_used: Option<super::Rate> = None;
    let mut index = 0usize;

    for (ep_index, ep) in exp.episodes.iter().enumerate() {
        let streams = views
            .iter()
            .map(|v| ViewStream::open(ep, v))
            .collect::<Result<Vec<_>>>()?;
        let rate = match fps_used {
            // One dataset has one rate: the first episode's, which later episodes must supply.
            Some(r) => choose_rate(Some(r.hz()), &source_rates(ep, &streams), &ep.name)?,
            None => choose_rate(options.fps, &source_rates(ep, &streams), &ep.name)?,
        };
        fps_used = Some(rate);
        let grid = episode_grid(ep, &streams, rate)?;
        let times = grid.times();
        let task_index = match tasks.iter().position(|t| t == &ep.task) {
            Some(i) => i,
            None => {
                tasks.push(ep.task.clone());
                tasks.len() - 1
            }
        };

        let mut rows = Rows::default();
        let mut prev_q = vec![None; nw];
        let mut last_opening = vec![None; nw];
        for (k, &t) in times.iter().enumerate() {
            rows.timestamp.push(rate.time(k) as f32);
            rows.t_session.push(t);
            for (w, wrist) in ep.wrists.iter().enumerate() {
                let s = wrist.sample_row(&ep.name, t)?;
                let state = wrist_state(&s, wrist.tool, &mut prev_q[w], &mut last_opening[w]);
                rows.state.extend(state.iter().map(|&v| v as f32));
                rows.support.push(support_code(s.support));
                rows.sigma
                    .extend([s.tip_sigma_p_m as f32, s.tip_sigma_r_rad as f32]);
                rows.confidence.push(s.opening_confidence as f32);
            }
        }
        // The action of a row is the next row's state; the last row holds its own.
        let n = times.len();
        rows.action = rows.state[width.min(rows.state.len())..].to_vec();
        rows.action
            .extend_from_slice(&rows.state[(n.saturating_sub(1)) * width..]);

        let (chunk, file) = (ep_index / CHUNKS_SIZE, ep_index % CHUNKS_SIZE);
        let mut table = Table::default();
        let mut stats: BTreeMap<String, Stats> = BTreeMap::new();
        for k in 0..n {
            let st = &rows.state[k * width..(k + 1) * width];
            let ac = &rows.action[k * width..(k + 1) * width];
            let f64s = |v: &[f32]| v.iter().map(|&x| f64::from(x)).collect::<Vec<f64>>();
            stats
                .entry("observation.state".into())
                .or_default()
                .add(&f64s(st));
            stats.entry("action".into()).or_default().add(&f64s(ac));
            stats
                .entry("timestamp".into())
                .or_default()
                .add(&[f64::from(rows.timestamp[k])]);
            stats
                .entry("frame_index".into())
                .or_default()
                .add(&[k as f64]);
            stats
                .entry("episode_index".into())
                .or_default()
                .add(&[ep_index as f64]);
            stats
                .entry("index".into())
                .or_default()
                .add(&[(index + k) as f64]);
            stats
                .entry("task_index".into())
                .or_default()
                .add(&[task_index as f64]);
            stats
                .entry("kiwi.t_session".into())
                .or_default()
                .add(&[rows.t_session[k]]);
            stats.entry("kiwi.support".into()).or_default().add(
                &rows.support[k * nw..(k + 1) * nw]
                    .iter()
                    .map(|&v| v as f64)
                    .collect::<Vec<_>>(),
            );
            stats
                .entry("kiwi.tip_sigma".into())
                .or_default()
                .add(&f64s(&rows.sigma[k * 2 * nw..(k + 1) * 2 * nw]));
            stats
                .entry("kiwi.gripper_confidence".into())
                .or_default()
                .add(&f64s(&rows.confidence[k * nw..(k + 1) * nw]));
        }
        table.f32_list("observation.state", width, rows.state)?;
        table.f32_list("action", width, rows.action)?;
        table.f32("timestamp", rows.timestamp);
        table.i64("frame_index", (0..n as i64).collect());
        table.i64("episode_index", vec![ep_index as i64; n]);
        table.i64("index", (index as i64..(index + n) as i64).collect());
        table.i64("task_index", vec![task_index as i64; n]);
        table.f64("kiwi.t_session", rows.t_session);
        table.i64_list("kiwi.support", nw, rows.support)?;
        table.f32_list("kiwi.tip_sigma", 2 * nw, rows.sigma)?;
        table.f32_list("kiwi.gripper_confidence", nw, rows.confidence)?;
        let path = dir.join(data_path(chunk, file));
        if let Some(parent) = path.parent() {
            create_dir(parent)?;
        }
        table.write(&path)?;

        let mut videos = Vec::new();
        let sampled = image_sample_rows(n);
        let mut summaries: BTreeMap<String, Summary> = stats
            .iter()
            .map(|(k, s)| (k.clone(), s.summary()))
            .collect();
        for stream in &streams {
            let key = format!("observation.images.{}", stream.view.key());
            let (picks, worst) = stream.nearest_frames(&times);
            report.max_frame_offset_s = report.max_frame_offset_s.max(worst);
            let path = dir.join(video_path(&key, chunk, file));
            if let Some(parent) = path.parent() {
                create_dir(parent)?;
            }
            let mut images = ImageStats::default();
            let size = encode_frames(&stream.source, &picks, rate, &path, |k, frame| {
                if sampled.binary_search(&k).is_ok() {
                    images.add(frame);
                }
            })?;
            summaries.insert(key.clone(), images.summary());
            image_stats.entry(key.clone()).or_default().merge(&images);
            video_info.insert(key.clone(), size);
            videos.push(key);
        }
        for (key, s) in stats {
            stats_all.entry(key).or_default().merge(&s);
        }
        tracing::info!(
            "export: episode {} as LeRobot episode {ep_index}: {n} rows at {:.4} Hz",
            ep.name,
            rate.hz()
        );
        episodes_meta.push(EpisodeMeta {
            episode_index: ep_index,
            name: ep.name.clone(),
            verdict: ep.quality.verdict.as_str().to_string(),
            task: ep.task.clone(),
            length: n,
            from_index: index,
            chunk,
            file,
            duration: rate.time(n),
            t0_session: grid.t0,
            videos,
            stats: summaries,
        });
        index += n;
        report.exported.push(ep.name.clone());
    }
    let rate = fps_used.unwrap_or(super::Rate { num: 30, den: 1 });
    report.frames = index;
    report.fps = Some(rate.hz());

    write_episodes_meta(dir, &episodes_meta)?;
    write_tasks(dir, &tasks)?;
    let stats_json: serde_json::Map<String, Value> = stats_all
        .iter()
        .map(|(k, s)| (k.clone(), s.summary().to_json()))
        .chain(
            image_stats
                .iter()
                .map(|(k, s)| (k.clone(), s.summary().to_json())),
        )
        .collect();
    crate::formats::results::write_json(&dir.join("meta/stats.json"), &stats_json)?;
    let info = info_json(
        &wrist_names,
        rate,
        &video_info,
        episodes_meta.len(),
        index,
        tasks.len(),
    );
    crate::formats::results::write_json(&dir.join("meta/info.json"), &info)?;
    Ok(report)
}

/// What `meta/episodes` records of an episode.
struct EpisodeMeta {
    episode_index: usize,
    name: String,
    verdict: String,
    task: String,
    length: usize,
    from_index: usize,
    chunk: usize,
    file: usize,
    duration: f64,
    t0_session: f64,
    videos: Vec<String>,
    /// Per feature statistics of the episode (`stats/<feature>/<stat>` columns).
    stats: BTreeMap<String, Summary>,
}

fn write_episodes_meta(dir: &Path, eps: &[EpisodeMeta]) -> Result<()> {
    let mut t = Table::default();
    let col = |f: &dyn Fn(&EpisodeMeta) -> usize| -> Vec<i64> {
        eps.iter().map(|e| f(e) as i64).collect()
    };
    t.i64("episode_index", col(&|e| e.episode_index));
    t.string_lists(
        "tasks",
        &eps.iter().map(|e| vec![e.task.clone()]).collect::<Vec<_>>(),
    );
    t.i64("length", col(&|e| e.length));
    t.i64("data/chunk_index", col(&|e| e.chunk));
    t.i64("data/file_index", col(&|e| e.file));
    t.i64("dataset_from_index", col(&|e| e.from_index));
    t.i64("dataset_to_index", col(&|e| e.from_index + e.length));
    if let Some(first) = eps.first() {
        for key in &first.videos {
            t.i64(&format!("videos/{key}/chunk_index"), col(&|e| e.chunk));
            t.i64(&format!("videos/{key}/file_index"), col(&|e| e.file));
            t.f64(
                &format!("videos/{key}/from_timestamp"),
                vec![0.0; eps.len()],
            );
            t.f64(
                &format!("videos/{key}/to_timestamp"),
                eps.iter().map(|e| e.duration).collect(),
            );
        }
    }
    if let Some(first) = eps.first() {
        for (key, summary) in &first.stats {
            let of = |e: &EpisodeMeta| e.stats.get(key).cloned();
            let all: Option<Vec<Summary>> = eps.iter().map(of).collect();
            let Some(all) = all else {
                return Err(crate::export::export_err(format!(
                    "episode statistics of {key} are missing for some episodes"
                )));
            };
            for (i, (name, _)) in summary.values().into_iter().enumerate() {
                let rows: Vec<Vec<f64>> = all.iter().map(|s| s.values()[i].1.to_vec()).collect();
                let column = format!("stats/{key}/{name}");
                if summary.per_channel {
                    t.f64_channel_lists(&column, &rows);
                } else {
                    t.f64_lists(&column, &rows);
                }
            }
            let counts: Vec<Vec<i64>> = all.iter().map(|s| vec![s.count as i64]).collect();
            t.i64_lists(&format!("stats/{key}/count"), &counts);
        }
    }
    t.i64("meta/episodes/chunk_index", vec![0; eps.len()]);
    t.i64("meta/episodes/file_index", vec![0; eps.len()]);
    t.string("kiwi/episode", eps.iter().map(|e| e.name.clone()).collect());
    t.string(
        "kiwi/verdict",
        eps.iter().map(|e| e.verdict.clone()).collect(),
    );
    t.f64(
        "kiwi/t0_session",
        eps.iter().map(|e| e.t0_session).collect(),
    );
    let path = dir.join("meta/episodes/chunk-000/file-000.parquet");
    if let Some(parent) = path.parent() {
        create_dir(parent)?;
    }
    t.write(&path)
}

/// `meta/tasks.parquet`: the task text is the pandas index (`__index_level_0__`, as pandas
/// writes a DataFrame's unnamed index), `task_index` the column.
fn write_tasks(dir: &Path, tasks: &[String]) -> Result<()> {
    let mut t = Table::default();
    t.i64("task_index", (0..tasks.len() as i64).collect());
    t.string("__index_level_0__", tasks.to_vec());
    let pandas = json!({
        "index_columns": ["__index_level_0__"],
        "column_indexes": [{"name": null, "field_name": null, "pandas_type": "unicode",
                            "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
             "numpy_type": "int64", "metadata": null},
            {"name": null, "field_name": "__index_level_0__", "pandas_type": "unicode",
             "numpy_type": "object", "metadata": null}
        ],
        "creator": {"library": "kiwi", "version": env!("CARGO_PKG_VERSION")},
        "pandas_version": "2.0.0"
    });
    t.metadata("pandas", pandas.to_string());
    t.write(&dir.join("meta/tasks.parquet"))
}

fn fps_json(rate: super::Rate) -> Value {
    if rate.den == 1 {
        json!(rate.num)
    } else {
        json!(rate.hz())
    }
}

fn info_json(
    wrists: &[&str],
    rate: super::Rate,
    videos: &BTreeMap<String, (usize, usize)>,
    episodes: usize,
    frames: usize,
    tasks: usize,
) -> Value {
    let names = state_names(wrists);
    let width = names.len();
    let scalar = |dtype: &str| json!({"dtype": dtype, "shape": [1], "names": null});
    let mut features = serde_json::Map::new();
    features.insert(
        "observation.state".into(),
        json!({"dtype": "float32", "shape": [width], "names": names}),
    );
    features.insert(
        "action".into(),
        json!({"dtype": "float32", "shape": [width], "names": names}),
    );
    for (key, (w, h)) in videos {
        features.insert(
            key.clone(),
            json!({
                "dtype": "video",
                "shape": [h, w, 3],
                "names": ["height", "width", "channels"],
                "info": {
                    "video.height": h,
                    "video.width": w,
                    "video.codec": VIDEO_CODEC,
                    "video.pix_fmt": PIX_FMT,
                    "video.is_depth_map": false,
                    "video.fps": fps_json(rate),
                    "video.channels": 3,
                    "video.g": KEYFRAME_INTERVAL,
                    "has_audio": false
                }
            }),
        );
    }
    features.insert("timestamp".into(), scalar("float32"));
    for key in ["frame_index", "episode_index", "index", "task_index"] {
        features.insert(key.into(), scalar("int64"));
    }
    features.insert("kiwi.t_session".into(), scalar("float64"));
    features.insert(
        "kiwi.support".into(),
        json!({"dtype": "int64", "shape": [wrists.len()], "names": wrists}),
    );
    let sigma_names: Vec<String> = wrists
        .iter()
        .flat_map(|w| [format!("{w}_tip_sigma_p_m"), format!("{w}_tip_sigma_r_rad")])
        .collect();
    features.insert(
        "kiwi.tip_sigma".into(),
        json!({"dtype": "float32", "shape": [2 * wrists.len()], "names": sigma_names}),
    );
    features.insert(
        "kiwi.gripper_confidence".into(),
        json!({"dtype": "float32", "shape": [wrists.len()], "names": wrists}),
    );
    let video_path_template = if videos.is_empty() {
        Value::Null
    } else {
        json!("videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4")
    };
    json!({
        "codebase_version": CODEBASE_VERSION,
        "robot_type": ROBOT_TYPE,
        "total_episodes": episodes,
        "total_frames": frames,
        "total_tasks": tasks,
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILES_SIZE_MB,
        "video_files_size_in_mb": VIDEO_FILES_SIZE_MB,
        "fps": fps_json(rate),
        "splits": {"train": format!("0:{episodes}")},
        "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
        "video_path": video_path_template,
        "features": features
    })
}
