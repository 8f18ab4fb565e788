//! The session report: `kiwi run` ends with the report page, `kiwi report` makes it again, and
//! a headless Chromium opens it from disk with no console message and every chart drawn (and
//! saves a screenshot). A session whose episodes all failed still gets a page that says why.
//!
//! Without Chromium (Debian package `chromium`, installed by `make deps`) the browser checks
//! are skipped with a loud message; the page's own checks still run.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

#[path = "support/pipeline_sessions.rs"]
mod sessions;

const KIWI: &str = env!("CARGO_BIN_EXE_kiwi");
/// Longest a headless Chromium may take to load the page and write its output; it is killed
/// after that and the test fails rather than hangs.
const BROWSER_TIMEOUT: Duration = Duration::from_secs(120);
/// Browser window for the screenshot (pixels): the top of the page, the first episode's charts.
const SCREENSHOT_WINDOW: &str = "1000,1400";
/// Drawing elements that show a chart has content.
const DRAWN: [&str; 5] = ["<rect", "<polyline", "<circle", "<path", "<text"];

/// The Chromium on PATH (`KIWI_CHROMIUM` names another).
fn chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("KIWI_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .flat_map(|dir| ["chromium", "chromium-browser"].map(|n| dir.join(n)))
        .find(|p| p.is_file())
}

fn skip_loudly(what: &str) {
    eprintln!(
        "\n*** SKIPPED: {what}: no Chromium found (install Debian's `chromium` with `make deps`, \
         or set KIWI_CHROMIUM) ***\n"
    );
}

/// Run Chromium headless on `page` with `args`, killing it after [`BROWSER_TIMEOUT`]; returns
/// its stdout and stderr.
fn run_chromium(browser: &Path, page: &Path, args: &[String], scratch: &Path) -> (String, String) {
    let profile = tempfile::tempdir_in(scratch).unwrap();
    let (out_path, err_path) = (scratch.join("chromium.out"), scratch.join("chromium.err"));
    let mut child = Command::new(browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-dev-shm-usage",
            "--no-first-run",
            "--enable-logging=stderr",
            "--v=0",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .args(args)
        .arg(format!("file://{}", page.canonicalize().unwrap().display()))
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&out_path).unwrap())
        .stderr(std::fs::File::create(&err_path).unwrap())
        .spawn()
        .unwrap();
    let started = Instant::now();
    loop {
        if child.try_wait().unwrap().is_some() {
            break;
        }
        if started.elapsed() > BROWSER_TIMEOUT {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "Chromium did not finish within {BROWSER_TIMEOUT:?} ({args:?}); stderr:\n{}",
                std::fs::read_to_string(&err_path).unwrap_or_default()
            );
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    (
        std::fs::read_to_string(&out_path).unwrap_or_default(),
        std::fs::read_to_string(&err_path).unwrap_or_default(),
    )
}

/// Console messages in Chromium's log (the page has no script: any is an error, as is a
/// resource that failed to load).
fn console_messages(log: &str) -> Vec<&str> {
    log.lines()
        .filter(|l| {
            l.contains(":CONSOLE") || l.contains("Uncaught") || l.contains("Failed to load")
        })
        .collect()
}

/// Open `page` in headless Chromium: no console message, every chart figure holds a drawn
/// SVG after load; save a screenshot to `screenshot`. Returns false (after saying so loudly)
/// when there is no Chromium.
fn check_in_chromium(page: &Path, screenshot: &Path, scratch: &Path) -> bool {
    let Some(browser) = chromium() else {
        skip_loudly("the browser check of the report page");
        return false;
    };
    let html = std::fs::read_to_string(page).unwrap();
    let expected = html.matches("data-plot=").count();

    let (dom, log) = run_chromium(&browser, page, &["--dump-dom".to_string()], scratch);
    let console = console_messages(&log);
    assert!(console.is_empty(), "console messages: {console:#?}");
    assert!(
        dom.contains("</html>"),
        "no DOM dumped; Chromium said:\n{log}"
    );
    let figures: Vec<&str> = dom.split("<figure class=\"plot\"").skip(1).collect();
    assert_eq!(figures.len(), expected, "figures in the loaded DOM");
    for (k, f) in figures.iter().enumerate() {
        let body = f.split("</figure>").next().unwrap_or("");
        let svg = body.split("<svg").nth(1).unwrap_or_else(|| {
            panic!(
                "figure {k} has no <svg> after load: {}",
                &body[..body.len().min(300)]
            )
        });
        assert!(
            DRAWN.iter().any(|d| svg.contains(d)),
            "figure {k}'s SVG is empty: {}",
            &svg[..svg.len().min(300)]
        );
    }
    assert_eq!(
        dom.matches("<svg").count(),
        expected,
        "an SVG outside a figure"
    );

    let _ = std::fs::remove_file(screenshot);
    let (_, log) = run_chromium(
        &browser,
        page,
        &[
            format!("--screenshot={}", screenshot.display()),
            format!("--window-size={SCREENSHOT_WINDOW}"),
            "--hide-scrollbars".to_string(),
        ],
        scratch,
    );
    let console = console_messages(&log);
    assert!(console.is_empty(), "console messages: {console:#?}");
    let size = std::fs::metadata(screenshot).map_or(0, |m| m.len());
    assert!(
        size > 10_000,
        "screenshot of {size} bytes; Chromium said:\n{log}"
    );
    println!(
        "Chromium drew {expected} charts; screenshot {} ({} kB)",
        screenshot.display(),
        size / 1000
    );
    true
}

fn stage<'a>(report: &'a serde_json::Value, name: &str) -> &'a serde_json::Value {
    report["stages"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["stage"] == name)
        .unwrap_or_else(|| panic!("no stage {name} in {report}"))
}

fn run_json(toml: &Path) -> (Option<i32>, serde_json::Value) {
    let out = Command::new(KIWI)
        .args(["run", "--json", "--session"])
        .arg(toml)
        .output()
        .unwrap();
    let report = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stderr)));
    (out.status.code(), report)
}

#[test]
#[ignore = "records and runs a mappable session (about 10 minutes): run on request with --run-ignored"]
fn the_run_ends_with_a_report_page_that_renders_in_chromium() {
    let tmp = tempfile::tempdir().unwrap();
    let started = Instant::now();
    let toml = sessions::small_session(&tmp.path().join("s"), 2);
    println!(
        "session recorded in {:.1} s",
        started.elapsed().as_secs_f64()
    );
    let (code, report) = run_json(&toml);
    println!(
        "kiwi run: {:.1} s, {}",
        started.elapsed().as_secs_f64(),
        report["counts"]
    );
    // The short tabletop episode may leave a camera off the session timeline (exit status 2):
    // the report is written either way.
    assert!(matches!(code, Some(0 | 2)), "{report}");
    assert_eq!(stage(&report, "session/report")["outcome"], "ran");
    let page = toml.parent().unwrap().join("report/index.html");
    let html = std::fs::read_to_string(&page).unwrap();
    println!("page: {} kB", html.len() / 1000);
    for ep in ["ep000", "ep001"] {
        assert!(html.contains(&format!("id=\"ep-{ep}\"")), "{ep} missing");
    }
    // Per episode: a top view, a timeline, the sync graph and both wrists' openings.
    for (kind, count) in [
        ("top-view", 2),
        ("timeline", 2),
        ("sync-graph", 2),
        ("gripper", 4),
    ] {
        assert_eq!(
            html.matches(&format!("data-plot=\"{kind}\"")).count(),
            count,
            "{kind} charts"
        );
    }
    for text in [
        "support front",
        "lens localized",
        "map-rear",
        "localize-left-front",
        "triangle",
    ] {
        assert!(html.contains(text), "{text} missing");
    }
    assert!(!html.contains("http://") && !html.contains("https://") && !html.contains("<script"));

    // A second run changes nothing, so the report is current.
    let (_, again) = run_json(&toml);
    assert_eq!(stage(&again, "session/report")["outcome"], "current");

    // `kiwi report` makes the same page anywhere.
    let copy = tmp.path().join("elsewhere/page.html");
    let out = Command::new(KIWI)
        .args(["report", "--session"])
        .arg(&toml)
        .arg("--out")
        .arg(&copy)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let made = std::fs::read_to_string(&copy).unwrap();
    assert_eq!(
        made.matches("data-plot=").count(),
        html.matches("data-plot=").count()
    );

    let screenshot = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("report-screenshot.png");
    if check_in_chromium(&page, &screenshot, tmp.path()) {
        println!(
            "copy {} to docs/report.png to update the docs",
            screenshot.display()
        );
    }
    println!("total {:.1} s", started.elapsed().as_secs_f64());
}

#[test]
fn a_session_whose_episodes_failed_still_gets_a_report_that_says_why() {
    let tmp = tempfile::tempdir().unwrap();
    let toml = sessions::unmappable_session(tmp.path());
    let (code, report) = run_json(&toml);
    assert_eq!(code, Some(2), "{report}");
    assert_eq!(stage(&report, "session/report")["outcome"], "ran");
    let page = toml.parent().unwrap().join("report/index.html");
    let html = std::fs::read_to_string(&page).unwrap();
    for ep in ["ep000", "ep001"] {
        let section = html
            .split(&format!("id=\"ep-{ep}\""))
            .nth(1)
            .unwrap_or_else(|| panic!("{ep} missing"));
        let section = section.split("<h2").next().unwrap_or("");
        assert!(
            section.contains("verdict unusable") && section.contains("map-rear"),
            "{ep}: {section}"
        );
        assert!(section.contains("No trajectory to draw"), "{ep}");
    }
    // The failed stage is listed with its reason.
    assert!(html.contains("<td class=\"unusable\">failed</td>"));
    check_in_chromium(&page, &tmp.path().join("failed-screenshot.png"), tmp.path());
}
