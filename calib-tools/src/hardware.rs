//! The printed hardware: generate the files that follow from `hardware/params.toml` (the
//! OpenSCAD parameter file, the tool definitions, the bill of materials and the printable-parts
//! tables), render every part with OpenSCAD, and check each STL: non-empty, closed (every edge
//! shared by exactly two triangles, once in each direction), inside the printer's build volume,
//! and, for holders and tools, carrying the one shared dovetail profile where the part says its
//! quick-release is.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use nalgebra::{Matrix4, Point3, Vector3};
use serde::Deserialize;

use kiwi_core::hardware::{GENERATED_HEADER, HardwareParams};

use crate::error::{CalibError, Result};

/// Probe offset from a profile edge (mm): well above the STL's coordinate rounding (OpenSCAD
/// writes about 6 significant digits) and below the smallest feature the probes look at.
const PROBE_OFFSET_MM: f64 = 0.08;
/// Triangles whose area is below this (mm²) are slivers OpenSCAD may emit; they still count for
/// the edge check but not as solid faces.
const SLIVER_AREA_MM2: f64 = 1e-9;

/// A repository's hardware files, relative to its root.
#[derive(Debug, Clone)]
pub struct HardwareLayout {
    /// The repository root.
    pub root: PathBuf,
}

impl HardwareLayout {
    /// The layout of a repository root.
    pub fn new(root: &Path) -> Self {
        Self {
            root: root.to_path_buf(),
        }
    }
    /// `hardware/params.toml`.
    pub fn params(&self) -> PathBuf {
        self.root.join("hardware/params.toml")
    }
    /// `hardware/bom.csv`.
    pub fn bom(&self) -> PathBuf {
        self.root.join("hardware/bom.csv")
    }
    /// `hardware/parts.csv`.
    pub fn parts(&self) -> PathBuf {
        self.root.join("hardware/parts.csv")
    }
    /// The folder with one OpenSCAD file per printed part.
    pub fn parts_dir(&self) -> PathBuf {
        self.root.join("hardware/scad/parts")
    }
}

/// One row of `hardware/bom.csv`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BomItem {
    /// `core` (the kit), `head` (optional head module) or `robot` (robot-side parts).
    pub group: String,
    /// Supplier-neutral item name.
    pub item: String,
    /// Quantity in the group.
    pub quantity: u32,
    /// Unit price (US$).
    pub unit_price_usd: f64,
    /// When the price was taken (`YYYY-MM` or `YYYY-MM-DD`).
    pub price_date: String,
    /// Where the price comes from (a source, or "estimate (not a quote)").
    pub price_source: String,
    /// What it is for.
    pub description: String,
}

/// One row of `hardware/parts.csv`.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrintedPart {
    /// Part name (`hardware/scad/parts/<part>.scad`).
    pub part: String,
    /// `core`, `head` or `robot`, as in the bill of materials.
    pub group: String,
    /// How many to print.
    pub quantity: u32,
    /// Filament.
    pub material: String,
    /// Infill (%).
    pub infill_percent: u32,
    /// Perimeters (walls).
    pub perimeters: u32,
    /// How to lay it on the bed.
    pub orientation: String,
    /// Whether supports are needed.
    pub supports: String,
    /// Notes.
    pub notes: String,
}

/// The groups of the bill of materials, in table order, with their headings.
const GROUPS: [(&str, &str); 3] = [
    (
        "core",
        "Kit: two wrist cameras, chopstick, parallel jaw, two cuffs",
    ),
    ("head", "Optional head module"),
    (
        "robot",
        "Optional robot side (flange adapter and robust holder)",
    ),
];

fn input(path: &Path, message: impl Into<String>) -> CalibError {
    CalibError::Input {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

fn read_csv<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<Vec<T>> {
    let text = kiwi_core::io::read_text(path)?;
    let mut reader = csv::Reader::from_reader(text.as_bytes());
    reader
        .deserialize()
        .enumerate()
        .map(|(i, row)| {
            row.map_err(|e| {
                input(
                    path,
                    format!("row {}: {e}; compare with the header line", i + 2),
                )
            })
        })
        .collect()
}

fn make_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|source| {
        CalibError::Core(kiwi_core::CoreError::Io {
            action: "creating folder",
            path: dir.to_path_buf(),
            source,
        })
    })
}

fn valid_date(s: &str) -> bool {
    let parts: Vec<&str> = s.split('-').collect();
    let digits = |p: &str, n: usize| p.len() == n && p.chars().all(|c| c.is_ascii_digit());
    match parts.as_slice() {
        [y, m] => digits(y, 4) && digits(m, 2),
        [y, m, d] => digits(y, 4) && digits(m, 2) && digits(d, 2),
        _ => false,
    }
}

/// Read and check the bill of materials: known groups, positive quantities, finite prices, a
/// date and a source on every price.
pub fn read_bom(path: &Path) -> Result<Vec<BomItem>> {
    let items: Vec<BomItem> = read_csv(path)?;
    if items.is_empty() {
        return Err(input(path, "no items; expected one row per item"));
    }
    for (i, it) in items.iter().enumerate() {
        let row = i + 2;
        if !GROUPS.iter().any(|(g, _)| *g == it.group) {
            return Err(input(
                path,
                format!(
                    "row {row}: group `{}`; expected core, head or robot",
                    it.group
                ),
            ));
        }
        if it.quantity == 0 || !(it.unit_price_usd.is_finite() && it.unit_price_usd >= 0.0) {
            return Err(input(
                path,
                format!(
                    "row {row}: quantity {} at US${}; expected a positive quantity and a price ≥ 0",
                    it.quantity, it.unit_price_usd
                ),
            ));
        }
        if !valid_date(&it.price_date) || it.price_source.trim().is_empty() {
            return Err(input(
                path,
                format!(
                    "row {row}: price date `{}`, source `{}`; every price needs a date (YYYY-MM or \
                     YYYY-MM-DD) and a source, or `estimate (not a quote)`",
                    it.price_date, it.price_source
                ),
            ));
        }
    }
    Ok(items)
}

/// Read the printable-parts list and check it names exactly the parts in `parts_dir`.
pub fn read_parts(path: &Path, parts_dir: &Path) -> Result<Vec<PrintedPart>> {
    let parts: Vec<PrintedPart> = read_csv(path)?;
    let files = part_files(parts_dir)?;
    let listed: Vec<&str> = parts.iter().map(|p| p.part.as_str()).collect();
    for f in &files {
        let name = part_name(f);
        if !listed.contains(&name.as_str()) {
            return Err(input(
                path,
                format!(
                    "no row for {}; add one (material, infill, orientation)",
                    f.display()
                ),
            ));
        }
    }
    for p in &parts {
        if !files.iter().any(|f| part_name(f) == p.part) {
            return Err(input(
                path,
                format!(
                    "row for `{}` but no {}/{}.scad",
                    p.part,
                    parts_dir.display(),
                    p.part
                ),
            ));
        }
        if !GROUPS.iter().any(|(g, _)| *g == p.group) || p.quantity == 0 {
            return Err(input(
                path,
                format!(
                    "`{}`: group `{}`, quantity {}; expected core, head or robot and a positive quantity",
                    p.part, p.group, p.quantity
                ),
            ));
        }
    }
    Ok(parts)
}

/// The part files (`*.scad`) of a folder, sorted.
pub fn part_files(parts_dir: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(parts_dir).map_err(|source| {
        CalibError::Core(kiwi_core::CoreError::Io {
            action: "listing",
            path: parts_dir.to_path_buf(),
            source,
        })
    })?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "scad"))
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(input(parts_dir, "no .scad part files"));
    }
    Ok(files)
}

fn part_name(path: &Path) -> String {
    path.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default()
}

fn money(v: f64) -> String {
    let cents = (v * 100.0).round() as i64;
    let (whole, frac) = (cents / 100, cents % 100);
    let digits = whole.to_string();
    let mut grouped = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i) % 3 == 0 {
            grouped.push(',');
        }
        grouped.push(c);
    }
    format!("{grouped}.{frac:02}")
}

/// The bill of materials as a Markdown page, with a subtotal per group and the kit totals.
pub fn bom_markdown(items: &[BomItem]) -> String {
    let mut s = format!(
        "<!-- {GENERATED_HEADER} (from hardware/bom.csv) -->\n# Bill of materials\n\n\
         Prices in US$ with the date each was taken. `estimate (not a quote)` marks a price set \
         without a supplier's quote on that date: check it before ordering. The printed parts \
         are listed in [parts.md](parts.md).\n"
    );
    let mut totals = HashMap::new();
    for (group, heading) in GROUPS {
        let rows: Vec<&BomItem> = items.iter().filter(|i| i.group == group).collect();
        if rows.is_empty() {
            continue;
        }
        s.push_str(&format!(
            "\n## {heading}\n\n| item | qty | for | unit (US$) | total (US$) | price date | source |\n|---|---:|---|---:|---:|---|---|\n"
        ));
        let mut total = 0.0;
        for r in rows {
            let line = r.unit_price_usd * f64::from(r.quantity);
            total += line;
            s.push_str(&format!(
                "| {} | {} | {} | {} | {} | {} | {} |\n",
                r.item,
                r.quantity,
                r.description,
                money(r.unit_price_usd),
                money(line),
                r.price_date,
                r.price_source
            ));
        }
        s.push_str(&format!(
            "| **subtotal** | | | | **{}** | | |\n",
            money(total)
        ));
        totals.insert(group, total);
    }
    let t = |g: &str| totals.get(g).copied().unwrap_or(0.0);
    s.push_str(&format!(
        "\n## Totals per kit\n\n| kit | total (US$) |\n|---|---:|\n| kit | {} |\n| kit + head module | {} |\n| kit + head module + robot side | {} |\n",
        money(t("core")),
        money(t("core") + t("head")),
        money(t("core") + t("head") + t("robot"))
    ));
    s
}

/// The printable-parts list as a Markdown page.
pub fn parts_markdown(parts: &[PrintedPart]) -> String {
    let mut s = format!(
        "<!-- {GENERATED_HEADER} (from hardware/parts.csv) -->\n# Printed parts\n\n\
         `make hardware` writes one STL per part to `build/hardware/`, already laid out for \
         printing as the orientation column says. 0.2 mm layers, 0.4 mm nozzle. The bill of \
         materials: [bom.md](bom.md).\n\n\
         | part | group | qty | material | infill | walls | orientation | supports | notes |\n\
         |---|---|---:|---|---:|---:|---|---|---|\n"
    );
    for p in parts {
        s.push_str(&format!(
            "| `{}` | {} | {} | {} | {} % | {} | {} | {} | {} |\n",
            p.part,
            p.group,
            p.quantity,
            p.material,
            p.infill_percent,
            p.perimeters,
            p.orientation,
            p.supports,
            p.notes
        ));
    }
    s
}

/// Every generated file (path relative to the root, text).
pub fn generated_files(layout: &HardwareLayout) -> Result<Vec<(PathBuf, String)>> {
    let params = HardwareParams::load(&layout.params())?;
    let generated = params.generate()?;
    let mut files = vec![(
        PathBuf::from("hardware/scad/params.scad"),
        generated.params_scad,
    )];
    for (name, text) in generated.tools {
        files.push((PathBuf::from(format!("hardware/tools/{name}.toml")), text));
    }
    files.push((
        PathBuf::from("hardware/head/hat.toml"),
        generated.head_mount,
    ));
    let bom = read_bom(&layout.bom())?;
    files.push((PathBuf::from("docs/hardware/bom.md"), bom_markdown(&bom)));
    let parts = read_parts(&layout.parts(), &layout.parts_dir())?;
    files.push((
        PathBuf::from("docs/hardware/parts.md"),
        parts_markdown(&parts),
    ));
    Ok(files)
}

/// The generated files that differ from what is on disk (missing files included).
pub fn stale_files(layout: &HardwareLayout) -> Result<Vec<PathBuf>> {
    Ok(generated_files(layout)?
        .into_iter()
        .filter(|(rel, text)| {
            std::fs::read_to_string(layout.root.join(rel)).map_or(true, |t| &t != text)
        })
        .map(|(rel, _)| rel)
        .collect())
}

/// Write every generated file (atomically); returns the ones that changed.
pub fn write_generated(layout: &HardwareLayout) -> Result<Vec<PathBuf>> {
    let stale = stale_files(layout)?;
    for (rel, text) in generated_files(layout)? {
        if stale.contains(&rel) {
            let path = layout.root.join(&rel);
            if let Some(dir) = path.parent() {
                make_dir(dir)?;
            }
            kiwi_core::io::write_atomic(&path, text.as_bytes())?;
        }
    }
    Ok(stale)
}

// ------------------------------------------------------------------------------- meshes

/// A triangle mesh read from an STL file (mm).
#[derive(Debug, Clone)]
pub struct Mesh {
    /// Distinct vertices.
    pub vertices: Vec<Point3<f64>>,
    /// Triangles as vertex indices.
    pub triangles: Vec<[usize; 3]>,
}

/// What the mesh check found.
#[derive(Debug, Clone, PartialEq)]
pub struct MeshReport {
    /// Triangles.
    pub triangles: usize,
    /// Edges used by one triangle only, or by more than two.
    pub bad_edges: usize,
    /// Edges whose two triangles run the same way (inconsistent orientation).
    pub flipped_edges: usize,
    /// Bounding box minimum (mm).
    pub min: [f64; 3],
    /// Bounding box maximum (mm).
    pub max: [f64; 3],
    /// Enclosed volume (mm³).
    pub volume_mm3: f64,
}

impl MeshReport {
    /// Every edge shared by exactly two triangles, in opposite directions.
    pub fn is_closed(&self) -> bool {
        self.triangles > 0 && self.bad_edges == 0 && self.flipped_edges == 0
    }

    /// Bounding box size (mm).
    pub fn size(&self) -> [f64; 3] {
        [0, 1, 2].map(|i| self.max[i] - self.min[i])
    }

    /// Whether the part fits a build volume as laid out (turning it about the vertical axis
    /// by 90° allowed).
    pub fn fits(&self, build_volume_mm: [f64; 3]) -> bool {
        let [x, y, z] = self.size();
        let [bx, by, bz] = build_volume_mm;
        z <= bz && ((x <= bx && y <= by) || (x <= by && y <= bx))
    }
}

impl Mesh {
    /// Read an ASCII or binary STL file.
    pub fn read(path: &Path) -> Result<Self> {
        let mut file = std::fs::File::open(path).map_err(|source| {
            CalibError::Core(kiwi_core::CoreError::Io {
                action: "reading",
                path: path.to_path_buf(),
                source,
            })
        })?;
        let indexed = stl_io::read_stl(&mut file).map_err(|e| {
            input(
                path,
                format!("not a readable STL file ({e}); render the part again"),
            )
        })?;
        Ok(Self {
            vertices: indexed
                .vertices
                .iter()
                .map(|v| Point3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2])))
                .collect(),
            triangles: indexed.faces.iter().map(|f| f.vertices).collect(),
        })
    }

    /// Edge use, bounding box and volume.
    pub fn report(&self) -> MeshReport {
        let mut edges: HashMap<(usize, usize), (u32, u32)> = HashMap::new();
        let mut volume = 0.0;
        for t in &self.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                let entry = edges.entry((a.min(b), a.max(b))).or_insert((0, 0));
                if a < b {
                    entry.0 += 1;
                } else {
                    entry.1 += 1;
                }
            }
            let [a, b, c] = t.map(|i| self.vertices[i].coords);
            volume += a.dot(&b.cross(&c)) / 6.0;
        }
        let bad_edges = edges.values().filter(|(f, r)| f + r != 2).count();
        let flipped_edges = edges.values().filter(|(f, r)| f + r == 2 && f != r).count();
        let mut min = [f64::INFINITY; 3];
        let mut max = [f64::NEG_INFINITY; 3];
        for v in &self.vertices {
            for i in 0..3 {
                min[i] = min[i].min(v[i]);
                max[i] = max[i].max(v[i]);
            }
        }
        MeshReport {
            triangles: self.triangles.len(),
            bad_edges,
            flipped_edges,
            min,
            max,
            volume_mm3: volume,
        }
    }

    /// Whether a point lies inside the closed mesh: the parity of crossings along three rays in
    /// different, irrational-looking directions, by majority (a ray grazing an edge miscounts
    /// at most one of them).
    pub fn contains(&self, p: Point3<f64>) -> bool {
        let dirs = [
            Vector3::new(0.5773, 0.4127, 0.7044),
            Vector3::new(-0.6312, 0.5219, 0.5737),
            Vector3::new(0.2236, -0.8451, 0.4857),
        ];
        let inside = dirs
            .iter()
            .filter(|d| self.crossings(p, &d.normalize()) % 2 == 1)
            .count();
        inside >= 2
    }

    fn crossings(&self, p: Point3<f64>, d: &Vector3<f64>) -> usize {
        self.triangles
            .iter()
            .filter(|t| {
                let [a, b, c] = t.map(|i| self.vertices[i]);
                let (e1, e2) = (b - a, c - a);
                let h = d.cross(&e2);
                let det = e1.dot(&h);
                if det.abs() < SLIVER_AREA_MM2 {
                    return false;
                }
                let s = p - a;
                let u = s.dot(&h) / det;
                let q = s.cross(&e1);
                let v = d.dot(&q) / det;
                let t = e2.dot(&q) / det;
                (0.0..=1.0).contains(&u) && v >= 0.0 && u + v <= 1.0 && t > 0.0
            })
            .count()
    }
}

// ------------------------------------------------------------------------------- rendering

/// Which side of the quick-release a part carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum QuickReleaseSide {
    /// The dovetail plate (holders).
    Plate,
    /// The clamp (tools, flange adapter).
    Clamp,
}

/// A quick-release feature a part reported while rendering.
#[derive(Debug, Clone, PartialEq)]
pub struct QuickReleaseFeature {
    /// Plate or clamp.
    pub side: QuickReleaseSide,
    /// `stl_from_q`: the feature's quick-release frame in the STL's coordinates (mm).
    pub stl_from_q: Matrix4<f64>,
}

/// A rendered part.
#[derive(Debug, Clone)]
pub struct RenderedPart {
    /// Part name.
    pub name: String,
    /// The STL written.
    pub stl: PathBuf,
    /// Quick-release features the part reported.
    pub quick_release: Vec<QuickReleaseFeature>,
}

/// Render one part file to STL with OpenSCAD (headless) and collect what it reports.
pub fn render_part(scad: &Path, out_dir: &Path) -> Result<RenderedPart> {
    let name = part_name(scad);
    make_dir(out_dir)?;
    let stl = out_dir.join(format!("{name}.stl"));
    let tmp = out_dir.join(format!(".{name}.tmp.stl"));
    let output = Command::new("openscad")
        .arg("-o")
        .arg(&tmp)
        .arg(scad)
        .output()
        .map_err(|e| {
            input(
                scad,
                format!(
                    "cannot run `openscad` ({e}); `make deps` installs it (Debian package openscad)"
                ),
            )
        })?;
    let log = String::from_utf8_lossy(&output.stderr).into_owned();
    if !output.status.success() || log.contains("ERROR:") {
        return Err(input(
            scad,
            format!("openscad failed ({}):\n{log}", output.status),
        ));
    }
    if log.contains("WARNING:") {
        return Err(input(
            scad,
            format!("openscad warned (fix the part):\n{log}"),
        ));
    }
    std::fs::rename(&tmp, &stl).map_err(|source| {
        CalibError::Core(kiwi_core::CoreError::Io {
            action: "writing",
            path: stl.clone(),
            source,
        })
    })?;
    let mut quick_release = Vec::new();
    for line in log.lines() {
        let Some(rest) = line
            .strip_prefix("ECHO: \"KIWI_QR ")
            .and_then(|r| r.strip_suffix('"'))
        else {
            continue;
        };
        let (side, matrix) = rest.split_once(' ').unwrap_or((rest, ""));
        let side = match side {
            "plate" => QuickReleaseSide::Plate,
            "clamp" => QuickReleaseSide::Clamp,
            other => {
                return Err(input(
                    scad,
                    format!("unknown quick-release side `{other}` in `{line}`"),
                ));
            }
        };
        let numbers: Vec<f64> = matrix
            .split(|c: char| c == '[' || c == ']' || c == ',' || c.is_whitespace())
            .filter(|s| !s.is_empty())
            .map(str::parse)
            .collect::<std::result::Result<_, _>>()
            .map_err(|e| input(scad, format!("cannot read the matrix in `{line}`: {e}")))?;
        if numbers.len() != 16 {
            return Err(input(scad, format!("expected a 4 x 4 matrix in `{line}`")));
        }
        quick_release.push(QuickReleaseFeature {
            side,
            stl_from_q: Matrix4::from_row_slice(&numbers),
        });
    }
    Ok(RenderedPart {
        name,
        stl,
        quick_release,
    })
}

/// One place the dovetail check looks, in the quick-release frame (mm), and whether the part
/// must be solid there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Probe {
    /// Point in Q.
    pub at: Point3<f64>,
    /// Solid (true) or empty (false).
    pub solid: bool,
    /// What the probe checks.
    pub what: &'static str,
}

/// Probes of the shared dovetail: just inside and just outside each working face of the
/// profile (contact face, straight edges, flanks), at two stations along the slide axis away
/// from the screws. A plate is solid inside its profile and empty outside it; a clamp is empty
/// inside its channel and solid just beyond it (floor, side walls, lips).
pub fn dovetail_probes(params: &HardwareParams, side: QuickReleaseSide) -> Vec<Probe> {
    let profile = match side {
        QuickReleaseSide::Plate => params.plate_profile_mm(),
        QuickReleaseSide::Clamp => params.channel_profile_mm(),
    };
    // Profile edges (counter-clockwise in x, z): [2] -> [3] right flank, [3] -> [4] right
    // edge, [4] -> [5] contact face, [5] -> [6] left edge, [6] -> [7] left flank.
    let faces = [
        (2, 3, "right flank"),
        (3, 4, "right edge"),
        (4, 5, "contact face"),
        (5, 6, "left edge"),
        (6, 7, "left flank"),
    ];
    let stations = [-0.25, 0.3].map(|f| f * params.quick_release.length_mm);
    let mut probes = Vec::new();
    for (i, j, what) in faces {
        let (a, b) = (profile[i], profile[j]);
        let (dx, dz) = (b[0] - a[0], b[1] - a[1]);
        let len = (dx * dx + dz * dz).sqrt();
        // Outward normal of a counter-clockwise polygon edge.
        let (nx, nz) = (dz / len, -dx / len);
        for along in [0.3, 0.7] {
            let (mx, mz) = (a[0] + along * dx, a[1] + along * dz);
            // The contact face is probed off-centre (the locking screw and stop slot sit on the
            // centre line).
            let mx = if what == "contact face" {
                (along - 0.5) * 2.0 * 0.6 * params.quick_release.width_mm / 2.0
            } else {
                mx
            };
            for y in stations {
                let inside = Point3::new(mx - nx * PROBE_OFFSET_MM, y, mz - nz * PROBE_OFFSET_MM);
                let outside = Point3::new(mx + nx * PROBE_OFFSET_MM, y, mz + nz * PROBE_OFFSET_MM);
                let plate = side == QuickReleaseSide::Plate;
                probes.push(Probe {
                    at: inside,
                    solid: plate,
                    what,
                });
                probes.push(Probe {
                    at: outside,
                    solid: !plate,
                    what,
                });
            }
        }
    }
    probes
}

/// Check that a rendered mesh carries the shared dovetail where its feature says; returns the
/// probes that failed.
pub fn failed_probes(
    mesh: &Mesh,
    params: &HardwareParams,
    feature: &QuickReleaseFeature,
) -> Vec<Probe> {
    dovetail_probes(params, feature.side)
        .into_iter()
        .filter(|p| {
            let at = feature.stl_from_q.transform_point(&p.at);
            mesh.contains(at) != p.solid
        })
        .collect()
}

/// Everything checked about one rendered part.
#[derive(Debug, Clone)]
pub struct PartCheck {
    /// The rendered part.
    pub part: RenderedPart,
    /// Its mesh report.
    pub report: MeshReport,
    /// Dovetail probes that failed.
    pub failed_probes: Vec<Probe>,
}

impl PartCheck {
    /// The problems found, as sentences (empty when the part is fine).
    pub fn problems(&self, params: &HardwareParams) -> Vec<String> {
        let mut out = Vec::new();
        let r = &self.report;
        if r.triangles == 0 {
            out.push("the STL is empty".into());
        }
        if !r.is_closed() {
            out.push(format!(
                "the mesh is not closed: {} edges not shared by exactly two triangles, {} with both triangles the same way",
                r.bad_edges, r.flipped_edges
            ));
        }
        if r.volume_mm3.is_nan() || r.volume_mm3 <= 0.0 {
            out.push(format!("enclosed volume {:.1} mm³", r.volume_mm3));
        }
        if !r.fits(params.printer.build_volume_mm) {
            let [x, y, z] = r.size();
            out.push(format!(
                "{x:.1} x {y:.1} x {z:.1} mm does not fit the {} ({:?} mm)",
                params.printer.name, params.printer.build_volume_mm
            ));
        }
        for p in &self.failed_probes {
            out.push(format!(
                "dovetail {}: expected {} at ({:.2}, {:.2}, {:.2}) in its quick-release frame",
                p.what,
                if p.solid { "material" } else { "no material" },
                p.at.x,
                p.at.y,
                p.at.z
            ));
        }
        out
    }
}

/// Render and check one part.
pub fn check_part(scad: &Path, out_dir: &Path, params: &HardwareParams) -> Result<PartCheck> {
    let part = render_part(scad, out_dir)?;
    let mesh = Mesh::read(&part.stl)?;
    let report = mesh.report();
    let failed_probes = part
        .quick_release
        .iter()
        .flat_map(|f| failed_probes(&mesh, params, f))
        .collect();
    Ok(PartCheck {
        part,
        report,
        failed_probes,
    })
}

/// Render and check every part of the layout into `out_dir` (in parallel).
pub fn check_all(layout: &HardwareLayout, out_dir: &Path) -> Result<Vec<PartCheck>> {
    use rayon::prelude::*;
    let params = HardwareParams::load(&layout.params())?;
    let files = part_files(&layout.parts_dir())?;
    files
        .par_iter()
        .map(|f| check_part(f, out_dir, &params))
        .collect()
}

/// A Markdown table of the checked parts: size, volume, filament mass at a density.
pub fn check_table(checks: &[PartCheck], density_g_cm3: f64) -> String {
    let mut s = String::from(
        "| part | triangles | size (mm) | volume (cm³) | solid mass (g) | quick-release |\n|---|---:|---|---:|---:|---|\n",
    );
    for c in checks {
        let [x, y, z] = c.report.size();
        let qr: Vec<&str> = c
            .part
            .quick_release
            .iter()
            .map(|f| match f.side {
                QuickReleaseSide::Plate => "plate",
                QuickReleaseSide::Clamp => "clamp",
            })
            .collect();
        s.push_str(&format!(
            "| {} | {} | {x:.1} x {y:.1} x {z:.1} | {:.1} | {:.0} | {} |\n",
            c.part.name,
            c.report.triangles,
            c.report.volume_mm3 / 1000.0,
            c.report.volume_mm3 / 1000.0 * density_g_cm3,
            if qr.is_empty() {
                "-".to_string()
            } else {
                qr.join(", ")
            }
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn cube_mesh() -> Mesh {
        let v = |x: f64, y: f64, z: f64| Point3::new(x, y, z);
        let vertices = vec![
            v(0., 0., 0.),
            v(1., 0., 0.),
            v(1., 1., 0.),
            v(0., 1., 0.),
            v(0., 0., 1.),
            v(1., 0., 1.),
            v(1., 1., 1.),
            v(0., 1., 1.),
        ];
        let triangles = vec![
            [0, 2, 1],
            [0, 3, 2],
            [4, 5, 6],
            [4, 6, 7],
            [0, 1, 5],
            [0, 5, 4],
            [1, 2, 6],
            [1, 6, 5],
            [2, 3, 7],
            [2, 7, 6],
            [3, 0, 4],
            [3, 4, 7],
        ];
        Mesh {
            vertices,
            triangles,
        }
    }

    #[test]
    fn a_cube_is_closed_and_contains_its_centre() {
        let m = cube_mesh();
        let r = m.report();
        assert!(r.is_closed(), "{r:?}");
        assert!((r.volume_mm3 - 1.0).abs() < 1e-12);
        assert!(m.contains(Point3::new(0.5, 0.5, 0.5)));
        assert!(m.contains(Point3::new(0.02, 0.98, 0.5)));
        assert!(!m.contains(Point3::new(1.02, 0.5, 0.5)));
        assert!(r.fits([1.0, 2.0, 1.0]));
        assert!(!r.fits([0.5, 2.0, 1.0]));
    }

    #[test]
    fn an_open_or_flipped_mesh_is_not_closed() {
        let mut m = cube_mesh();
        m.triangles.pop();
        assert_eq!(m.report().bad_edges, 3);
        let mut m = cube_mesh();
        m.triangles[0] = [0, 1, 2];
        let r = m.report();
        assert!(!r.is_closed() && r.flipped_edges > 0, "{r:?}");
    }

    #[test]
    fn money_groups_thousands() {
        assert_eq!(money(1099.98), "1,099.98");
        assert_eq!(money(0.05), "0.05");
        assert_eq!(money(12345678.5), "12,345,678.50");
    }

    #[test]
    fn bom_rows_need_a_dated_source() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bom.csv");
        let header = "group,item,quantity,unit_price_usd,price_date,price_source,description\n";
        std::fs::write(
            &path,
            format!("{header}core,Thing,2,1.5,2026-12-01,estimate (not a quote),x\n"),
        )
        .unwrap();
        let items = read_bom(&path).unwrap();
        assert!(bom_markdown(&items).contains("| kit | 3.00 |"));
        std::fs::write(&path, format!("{header}core,Thing,2,1.5,,,x\n")).unwrap();
        let e = read_bom(&path).unwrap_err();
        assert!(e.to_string().contains("date"), "{e}");
    }
}

/// `kiwi-calib hardware …`.
pub mod cli {
    use std::path::PathBuf;

    use super::{HardwareLayout, check_all, check_table, stale_files, write_generated};
    use crate::error::{CalibError, Result};
    use kiwi_core::hardware::HardwareParams;

    /// Density of PETG (g/cm³) for the solid-mass column.
    const PETG_DENSITY_G_CM3: f64 = 1.27;

    /// The hardware commands.
    #[derive(Debug, clap::Subcommand)]
    pub enum HardwareCommand {
        /// Write the files that follow from hardware/params.toml (hardware/scad/params.scad,
        /// hardware/tools/*.toml) and the bill-of-materials and printed-parts pages
        /// (docs/hardware/); with --check, only report which are out of date (exit 1).
        Generate {
            /// Repository root.
            #[arg(long, default_value = ".")]
            root: PathBuf,
            /// Report stale files and fail instead of writing them.
            #[arg(long)]
            check: bool,
        },
        /// Render every part (hardware/scad/parts/*.scad) to STL with OpenSCAD and check each:
        /// non-empty, closed, inside the printer's build volume, the shared dovetail in place.
        Render {
            /// Repository root.
            #[arg(long, default_value = ".")]
            root: PathBuf,
            /// Folder for the STL files.
            #[arg(long, default_value = "build/hardware")]
            out: PathBuf,
        },
    }

    /// Run a hardware command; returns the text to print.
    pub fn run(cmd: &HardwareCommand) -> Result<String> {
        match cmd {
            HardwareCommand::Generate { root, check } => {
                let layout = HardwareLayout::new(root);
                if *check {
                    let stale = stale_files(&layout)?;
                    if stale.is_empty() {
                        return Ok("generated hardware files are up to date\n".into());
                    }
                    let list: Vec<String> = stale.iter().map(|p| p.display().to_string()).collect();
                    return Err(CalibError::Input {
                        path: layout.params(),
                        message: format!(
                            "out of date: {}; run `kiwi-calib hardware generate` (or `make hardware`)",
                            list.join(", ")
                        ),
                    });
                }
                let written = write_generated(&layout)?;
                Ok(if written.is_empty() {
                    "generated hardware files were up to date\n".into()
                } else {
                    let list: Vec<String> =
                        written.iter().map(|p| p.display().to_string()).collect();
                    format!("wrote {}\n", list.join(", "))
                })
            }
            HardwareCommand::Render { root, out } => {
                let layout = HardwareLayout::new(root);
                let params = HardwareParams::load(&layout.params())?;
                let checks = check_all(&layout, out)?;
                let mut text = check_table(&checks, PETG_DENSITY_G_CM3);
                let mut problems = Vec::new();
                for c in &checks {
                    for p in c.problems(&params) {
                        problems.push(format!("{}: {p}", c.part.name));
                    }
                }
                if !problems.is_empty() {
                    return Err(CalibError::Input {
                        path: out.clone(),
                        message: format!("{text}\n{}", problems.join("\n")),
                    });
                }
                text.push_str(&format!(
                    "\n{} parts in {}: closed, inside the {} build volume, dovetails in place\n",
                    checks.len(),
                    out.display(),
                    params.printer.name
                ));
                Ok(text)
            }
        }
    }
}
