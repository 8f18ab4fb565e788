//! The stage graph of a session (paper §4, `fig:pipeline`).
//!
//! Per session, on the session's `map_episode` (after that episode's `sync`):
//! `map-rear` (the shared scene map, from one wrist's rear stream) and `map-front-<wrist>`,
//! `tool-<wrist>` (the tool's dot plane from its body tag), then — from that episode's own
//! localizations — `metric-rear` / `metric-front-<wrist>` (scale, gravity, biases) and
//! `placement-<wrist>` (`G_a`, eq. 2). The mapping episode's rear stream of the wrist that did not
//! build the rear map also reads, optionally, the map wrist's front map, metric recoveries and
//! placement: the witness that decides between its runs where they do not join
//! ([`rear_witness_deps`]); that wrist's `placement-<wrist>` reads the same, and pools the
//! witness's pairs into its fit.
//!
//! Per episode, once the maps are frozen: `sync` → `localize-<wrist>-<lens>` (four streams, no map
//! updates; after the map episode a front stream also starts from the poses its wrist's rear
//! lens gives, so it waits for that stream, the metric maps and the placement) →
//! `observations-<wrist>` (eq. 3; it reads, optionally, the other wrist's front map, metric
//! recovery and placement, the third vote where its two lenses disagree:
//! [`other_front_map_deps`]) → `fusion-<wrist>` (eq. 4) → `gripper-<wrist>` →
//! `outputs` (tool tip on the session timeline, TUM files, `quality.json`). With a head camera,
//! `head` (the hat marker in both rear streams, fused into the head's track, and the head
//! camera's poses) runs after both wrists' fusion and before `outputs`, which publishes it.
//!
//! Per session, when `session.toml` has an `[export]` table and the run covers every episode:
//! `export-<format>` (a dataset of every usable episode, from the episodes' published `out/`),
//! after every episode's `outputs`.
//!
//! Per session, when the run covers every episode: `report` (the session's HTML report page,
//! `report/index.html`), last, after every episode's `outputs` and every export. It reads
//! what the stages before it left, failed ones included.
//!
//! `floor` (the floor reference from both wrists' front streams, §4.3.3) runs after both
//! wrists' fusion and before `outputs`, which adds each camera's and tool tip's height above the
//! floor and publishes it.

use kiwi_core::layout::Side;

use crate::export::ExportFormat;

use super::context::SessionContext;
use super::stage::StageId;

/// A lens of a wrist unit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Lens {
    /// Faces the tool.
    Front,
    /// Faces the room.
    Rear,
}

impl Lens {
    /// `front` or `rear`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Front => "front",
            Self::Rear => "rear",
        }
    }
}

/// Which map: the shared rear (scene) map or a wrist's front map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum MapName {
    /// The shared rear map, built from the map wrist's rear stream.
    Rear,
    /// A wrist's front map.
    Front(Side),
}

impl MapName {
    /// `rear` or `front-left`.
    pub fn label(self) -> String {
        match self {
            Self::Rear => "rear".into(),
            Self::Front(side) => format!("front-{}", side.camera_name()),
        }
    }

    /// The map a lens of a wrist is localized in.
    pub fn for_lens(side: Side, lens: Lens) -> Self {
        match lens {
            Lens::Front => Self::Front(side),
            Lens::Rear => Self::Rear,
        }
    }
}

/// What a stage does, with what it does it on.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum StageKind {
    /// Audio time sync of an episode's cameras (§4.1).
    Sync {
        /// Episode.
        episode: String,
    },
    /// Build a map from the map episode (§4.2).
    Map {
        /// Which map.
        map: MapName,
    },
    /// Calibrate a wrist's tool (dot plane from the body tag) on the map episode (§4.3.1).
    Tool {
        /// Wrist.
        side: Side,
    },
    /// Localize one lens stream of an episode in its frozen map.
    Localize {
        /// Episode.
        episode: String,
        /// Wrist.
        side: Side,
        /// Lens.
        lens: Lens,
    },
    /// Metric recovery of a map from the map episode's localizations and IMU.
    Metric {
        /// Which map.
        map: MapName,
    },
    /// Scene placement `G_a` of a wrist's front map (eq. 2).
    Placement {
        /// Wrist.
        side: Side,
    },
    /// Body observations of a wrist in an episode (eq. 3).
    Observations {
        /// Episode.
        episode: String,
        /// Wrist.
        side: Side,
    },
    /// Per-wrist visual–inertial fusion (eq. 4).
    Fusion {
        /// Episode.
        episode: String,
        /// Wrist.
        side: Side,
    },
    /// Gripper opening per front frame (§4.3.1).
    Gripper {
        /// Episode.
        episode: String,
        /// Wrist.
        side: Side,
    },
    /// The head's track from the hat marker in both rear streams, and the head camera's poses
    /// (§4.3.2), when the session has a head camera.
    Head {
        /// Episode.
        episode: String,
    },
    /// The floor and other horizontal surfaces from both wrists' front streams (§4.3.3).
    Floor {
        /// Episode.
        episode: String,
    },
    /// The episode's deliverables: tool-tip trajectories, TUM files, `quality.json`.
    Outputs {
        /// Episode.
        episode: String,
    },
    /// A dataset of the session's usable episodes in one format (`[export]` of
    /// `session.toml`), published as `exports/<format>/`.
    Export {
        /// The dataset format.
        format: ExportFormat,
    },
    /// The session's report page (`report/index.html`): paths, support, sync, gripper,
    /// verdicts and stage timings of every episode.
    Report,
}

/// One node of the graph.
#[derive(Debug, Clone)]
pub struct StageNode {
    /// Its identity and folder.
    pub id: StageId,
    /// What it does.
    pub kind: StageKind,
    /// Stages whose outputs it reads.
    pub deps: Vec<StageId>,
    /// Those of `deps` it can do without: when one fails the stage still runs, without what
    /// that stage would have given it.
    pub optional: Vec<StageId>,
}

/// The stages whose outputs witness where the rear lens of `side` stands in the mapping
/// episode, when that wrist did not build the rear map: the map wrist's front map, its metric
/// recovery, the rear map's and that wrist's placement, through which this wrist's front lens,
/// seen in that front map, places its rear lens in the scene
/// ([`crate::vision::episode::Witness`]). Empty for the map wrist, whose rear stream built the
/// map it is localized in.
pub fn rear_witness_deps(ctx: &SessionContext, side: Side) -> Vec<StageId> {
    if side == ctx.map_side() {
        return Vec::new();
    }
    other_front_map_deps(ctx, side)
}

/// The stages through which the other wrist's front map places the front lens of `side` in
/// the scene: that wrist's front map, its metric recovery, the rear map's and that wrist's
/// placement. The witness of `side`'s rear runs in the mapping episode ([`rear_witness_deps`])
/// and of its body observations where its two lenses disagree
/// ([`crate::observations::SceneWitness`]). Empty with one wrist.
pub fn other_front_map_deps(ctx: &SessionContext, side: Side) -> Vec<StageId> {
    let other = side.other();
    if !ctx.wrists.contains_key(&other) {
        return Vec::new();
    }
    vec![
        id_of(&StageKind::Map {
            map: MapName::Front(other),
        }),
        id_of(&StageKind::Metric {
            map: MapName::Front(other),
        }),
        id_of(&StageKind::Metric { map: MapName::Rear }),
        id_of(&StageKind::Placement { side: other }),
    ]
}

/// `stages` without the rear map's metric recovery (for a stage that cannot do without it).
fn without_rear_metric(stages: Vec<StageId>) -> Vec<StageId> {
    let rear = id_of(&StageKind::Metric { map: MapName::Rear });
    stages.into_iter().filter(|s| *s != rear).collect()
}

/// The id of a stage kind.
pub fn id_of(kind: &StageKind) -> StageId {
    match kind {
        StageKind::Sync { episode } => StageId::episode(episode, "sync"),
        StageKind::Map { map } => StageId::session(format!("map-{}", map.label())),
        StageKind::Tool { side } => StageId::session(format!("tool-{}", side.camera_name())),
        StageKind::Localize {
            episode,
            side,
            lens,
        } => StageId::episode(
            episode,
            format!("localize-{}-{}", side.camera_name(), lens.name()),
        ),
        StageKind::Metric { map } => StageId::session(format!("metric-{}", map.label())),
        StageKind::Placement { side } => {
            StageId::session(format!("placement-{}", side.camera_name()))
        }
        StageKind::Observations { episode, side } => {
            StageId::episode(episode, format!("observations-{}", side.camera_name()))
        }
        StageKind::Fusion { episode, side } => {
            StageId::episode(episode, format!("fusion-{}", side.camera_name()))
        }
        StageKind::Gripper { episode, side } => {
            StageId::episode(episode, format!("gripper-{}", side.camera_name()))
        }
        StageKind::Head { episode } => StageId::episode(episode, "head"),
        StageKind::Floor { episode } => StageId::episode(episode, "floor"),
        StageKind::Outputs { episode } => StageId::episode(episode, "outputs"),
        StageKind::Export { format } => StageId::session(format!("export-{}", format.name())),
        StageKind::Report => StageId::session("report"),
    }
}

/// The stages of one wrist that an episode's outputs read: its localizations, observations,
/// fusion and gripper openings in the episode, its front map's metric recovery and its
/// placement. When one of them fails the outputs publish the other wrist, and the episode is
/// `unusable` with the reason.
pub fn wrist_output_deps(ctx: &SessionContext, episode: &str, side: Side) -> Vec<StageId> {
    let on = |kind: StageKind| id_of(&kind);
    let episode = episode.to_string();
    let mut v = vec![
        on(StageKind::Localize {
            episode: episode.clone(),
            side,
            lens: Lens::Front,
        }),
        on(StageKind::Localize {
            episode: episode.clone(),
            side,
            lens: Lens::Rear,
        }),
        on(StageKind::Observations {
            episode: episode.clone(),
            side,
        }),
        on(StageKind::Fusion {
            episode: episode.clone(),
            side,
        }),
        on(StageKind::Metric {
            map: MapName::Front(side),
        }),
        on(StageKind::Placement { side }),
    ];
    if ctx.wrists.get(&side).is_some_and(|w| w.tool.is_some()) {
        v.push(on(StageKind::Gripper { episode, side }));
    }
    v
}

/// What an episode's outputs can do without: each wrist's stages ([`wrist_output_deps`]; at
/// least one wrist must remain) and the head and floor stages (which read both wrists).
fn outputs_optional_deps(ctx: &SessionContext, episode: &str) -> Vec<StageId> {
    let mut v: Vec<StageId> = (ctx.wrists.keys())
        .flat_map(|&side| wrist_output_deps(ctx, episode, side))
        .collect();
    if ctx.session.head.is_some() {
        v.push(StageId::episode(episode, "head"));
    }
    v.push(StageId::episode(episode, "floor"));
    v
}

/// Stage families a user can name in `--from`, `--force` and `kiwi status`.
pub const FAMILIES: [&str; 14] = [
    "sync",
    "map",
    "tool",
    "localize",
    "metric",
    "placement",
    "observations",
    "fusion",
    "gripper",
    "head",
    "floor",
    "outputs",
    "export",
    "report",
];

/// The session's stage families that run after every episode's outputs (datasets, the
/// report): their folders are not pipeline results, and a run of them alone (`--only`) is
/// what follows a cluster's episode tasks.
pub const AFTER_EPISODE_FAMILIES: [&str; 2] = ["export", "report"];

/// The graph for `episodes` (the session's stages and the map episode's localizations are
/// always included: every episode needs them), in an order where every stage follows its
/// dependencies.
pub fn build(ctx: &SessionContext, episodes: &[String]) -> Vec<StageNode> {
    let mut nodes: Vec<StageNode> = Vec::new();
    let map_ep = ctx.session.map_episode.clone();
    // The other wrist's rear lens in the mapping episode is placed by a witness where its runs
    // conflict; it runs without the witness when the witness's stages fail.
    let optional_of = |kind: &StageKind| match kind {
        StageKind::Localize {
            episode,
            side,
            lens: Lens::Rear,
        } if *episode == map_ep => rear_witness_deps(ctx, *side),
        // The wrist that did not build the rear map pools the other wrist's front map into its
        // placement; both stages need the rear map's metric recovery anyway.
        StageKind::Placement { side } => without_rear_metric(rear_witness_deps(ctx, *side)),
        // Where a wrist's two lenses disagree, the other wrist's front map is the third vote.
        StageKind::Observations { side, .. } => {
            without_rear_metric(other_front_map_deps(ctx, *side))
        }
        StageKind::Outputs { episode } => outputs_optional_deps(ctx, episode),
        _ => Vec::new(),
    };
    let mut push = |kind: StageKind, deps: Vec<StageId>| {
        let id = id_of(&kind);
        if !nodes.iter().any(|n| n.id == id) {
            let optional = optional_of(&kind);
            let mut deps = deps;
            for o in &optional {
                if !deps.contains(o) {
                    deps.push(o.clone());
                }
            }
            nodes.push(StageNode {
                id,
                kind,
                deps,
                optional,
            });
        }
    };
    let sides: Vec<Side> = ctx.wrists.keys().copied().collect();
    let map_side = ctx.map_side();
    let mut maps = vec![MapName::Rear];
    maps.extend(sides.iter().map(|&s| MapName::Front(s)));

    // Session: maps and tools from the map episode.
    for &map in &maps {
        push(StageKind::Map { map }, Vec::new());
    }
    for &side in &sides {
        if ctx.wrists.get(&side).is_some_and(|w| w.tool.is_some()) {
            push(StageKind::Tool { side }, Vec::new());
        }
    }
    // The map episode's localizations feed metric recovery and placement.
    let localize = |episode: &str, side: Side, lens: Lens| StageKind::Localize {
        episode: episode.to_string(),
        side,
        lens,
    };
    for &side in &sides {
        for lens in [Lens::Front, Lens::Rear] {
            let kind = localize(&map_ep, side, lens);
            let dep = id_of(&StageKind::Map {
                map: MapName::for_lens(side, lens),
            });
            push(kind, vec![dep]);
        }
    }
    for &map in &maps {
        let (side, lens) = match map {
            MapName::Rear => (map_side, Lens::Rear),
            MapName::Front(s) => (s, Lens::Front),
        };
        push(
            StageKind::Metric { map },
            vec![id_of(&localize(&map_ep, side, lens))],
        );
    }
    for &side in &sides {
        push(
            StageKind::Placement { side },
            vec![
                id_of(&localize(&map_ep, side, Lens::Front)),
                id_of(&localize(&map_ep, side, Lens::Rear)),
                id_of(&StageKind::Metric {
                    map: MapName::Front(side),
                }),
                id_of(&StageKind::Metric { map: MapName::Rear }),
            ],
        );
    }

    // Episodes.
    for episode in episodes {
        push(
            StageKind::Sync {
                episode: episode.clone(),
            },
            Vec::new(),
        );
        for &side in &sides {
            // After the map episode, a front stream is also tried around the poses its rear
            // lens gives (through the frozen metric maps and the placement).
            push(
                localize(episode, side, Lens::Rear),
                vec![id_of(&StageKind::Map { map: MapName::Rear })],
            );
            push(
                localize(episode, side, Lens::Front),
                vec![
                    id_of(&StageKind::Map {
                        map: MapName::Front(side),
                    }),
                    id_of(&localize(episode, side, Lens::Rear)),
                    id_of(&StageKind::Metric {
                        map: MapName::Front(side),
                    }),
                    id_of(&StageKind::Metric { map: MapName::Rear }),
                    id_of(&StageKind::Placement { side }),
                ],
            );
            push(
                StageKind::Observations {
                    episode: episode.clone(),
                    side,
                },
                // The maps: where the two lenses disagree, each is tried where the other
                // places the wrist.
                vec![
                    id_of(&localize(episode, side, Lens::Front)),
                    id_of(&localize(episode, side, Lens::Rear)),
                    id_of(&StageKind::Metric {
                        map: MapName::Front(side),
                    }),
                    id_of(&StageKind::Metric { map: MapName::Rear }),
                    id_of(&StageKind::Placement { side }),
                    id_of(&StageKind::Map {
                        map: MapName::Front(side),
                    }),
                    id_of(&StageKind::Map { map: MapName::Rear }),
                ],
            );
            push(
                StageKind::Fusion {
                    episode: episode.clone(),
                    side,
                },
                vec![
                    id_of(&StageKind::Observations {
                        episode: episode.clone(),
                        side,
                    }),
                    id_of(&StageKind::Placement { side }),
                ],
            );
            if ctx.wrists.get(&side).is_some_and(|w| w.tool.is_some()) {
                push(
                    StageKind::Gripper {
                        episode: episode.clone(),
                        side,
                    },
                    vec![id_of(&StageKind::Tool { side })],
                );
            }
        }
        let mut deps = vec![id_of(&StageKind::Sync {
            episode: episode.clone(),
        })];
        for &side in &sides {
            deps.push(id_of(&StageKind::Fusion {
                episode: episode.clone(),
                side,
            }));
            deps.push(id_of(&localize(episode, side, Lens::Front)));
            deps.push(id_of(&localize(episode, side, Lens::Rear)));
            deps.push(id_of(&StageKind::Observations {
                episode: episode.clone(),
                side,
            }));
            if ctx.wrists.get(&side).is_some_and(|w| w.tool.is_some()) {
                deps.push(id_of(&StageKind::Gripper {
                    episode: episode.clone(),
                    side,
                }));
            }
        }
        for &map in &maps {
            deps.push(id_of(&StageKind::Metric { map }));
        }
        for &side in &sides {
            deps.push(id_of(&StageKind::Placement { side }));
        }
        // The head and the floor read the episode's clocks and both wrists' fused trajectories.
        let after_fusion: Vec<StageId> = std::iter::once(id_of(&StageKind::Sync {
            episode: episode.clone(),
        }))
        .chain(sides.iter().map(|&side| {
            id_of(&StageKind::Fusion {
                episode: episode.clone(),
                side,
            })
        }))
        .collect();
        if ctx.session.head.is_some() {
            let head = StageKind::Head {
                episode: episode.clone(),
            };
            deps.push(id_of(&head));
            push(head, after_fusion.clone());
        }
        let floor = StageKind::Floor {
            episode: episode.clone(),
        };
        deps.push(id_of(&floor));
        push(floor, after_fusion);
        push(
            StageKind::Outputs {
                episode: episode.clone(),
            },
            deps,
        );
    }

    // Session: dataset exports, only on a run of every episode (a run of some episodes must
    // not rewrite a dataset of all of them with a part).
    let all = ctx.episode_names();
    if let Some(config) = &ctx.session.export
        && all.iter().all(|e| episodes.contains(e))
    {
        let deps: Vec<StageId> = all
            .iter()
            .map(|episode| {
                id_of(&StageKind::Outputs {
                    episode: episode.clone(),
                })
            })
            .collect();
        for name in &config.formats {
            // `Session::validate` admits only the known names.
            if let Ok(format) = name.parse::<ExportFormat>() {
                push(StageKind::Export { format }, deps.clone());
            }
        }
    }
    // Session: the report, last, on a run of every episode (like the exports). It reads every
    // episode's sync, localizations and outputs, the scene map and its metric recovery, and
    // follows the exports so that its stage timings include them.
    if all.iter().all(|e| episodes.contains(e)) {
        let deps: Vec<StageId> = nodes
            .iter()
            .filter(|n| {
                matches!(
                    n.kind,
                    StageKind::Sync { .. }
                        | StageKind::Localize { .. }
                        | StageKind::Outputs { .. }
                        | StageKind::Export { .. }
                        | StageKind::Map { map: MapName::Rear }
                        | StageKind::Metric { map: MapName::Rear }
                )
            })
            .map(|n| n.id.clone())
            .collect();
        nodes.push(StageNode {
            id: id_of(&StageKind::Report),
            kind: StageKind::Report,
            deps,
            optional: Vec::new(),
        });
    }
    order(nodes)
}

/// Topological order (stable: among ready stages, the order they were added).
fn order(nodes: Vec<StageNode>) -> Vec<StageNode> {
    let mut done: Vec<StageId> = Vec::new();
    let mut pending = nodes;
    let mut out = Vec::with_capacity(pending.len());
    while !pending.is_empty() {
        let before = pending.len();
        let mut rest = Vec::new();
        for n in pending {
            if n.deps.iter().all(|d| done.contains(d)) {
                done.push(n.id.clone());
                out.push(n);
            } else {
                rest.push(n);
            }
        }
        if rest.len() == before {
            // Unreachable with the builder above; keep the remaining stages rather than loop.
            out.extend(rest);
            break;
        }
        pending = rest;
    }
    out
}
