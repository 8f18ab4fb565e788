//! `kiwi batch` on a real single-node Slurm cluster that the test starts (Debian's `slurm-wlm`
//! and `munge`, installed by `make deps`; no cgroups, no accounting; every file in a temporary
//! folder): a simulated session's plan is submitted, one array task is cancelled mid-run
//! (`scancel`), `kiwi batch status` names the cancelled episode and the episode whose stream is
//! corrupt (with its own error), `resubmit` submits only those two, and every episode's outputs
//! end byte-identical to a local `kiwi run`. The test stops its daemons.
//!
//! It needs root (the daemons run as root) and the Slurm and munge programs; without them it
//! says so on stderr and passes without checking.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

#[path = "support/pipeline_sessions.rs"]
mod sessions;
use sessions::{copy_inputs, files, localizing, small_session};

const KIWI: &str = env!("CARGO_BIN_EXE_kiwi");
/// Longest the cluster may take to come up (s).
const CLUSTER_START: Duration = Duration::from_secs(90);
/// Longest a plan's jobs may take to leave the queue.
const JOBS_END: Duration = Duration::from_secs(900);
/// The corrupt episode and the one cancelled mid-run.
const CORRUPT: &str = "ep003";
const CANCELLED: &str = "ep001";

fn which(program: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {program}")])
        .stdout(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// munged, slurmctld and slurmd, stopped (killed) when dropped. Every address is 127.0.0.1, so
/// the machine's host name need not resolve.
struct Cluster {
    conf: PathBuf,
    daemons: Vec<Child>,
    dir: PathBuf,
}

impl Drop for Cluster {
    fn drop(&mut self) {
        for d in self.daemons.iter_mut().rev() {
            let _ = d.kill();
            let _ = d.wait();
        }
    }
}

impl Cluster {
    fn start(dir: &Path) -> Cluster {
        std::fs::create_dir_all(dir).unwrap();
        let dir = dir.canonicalize().unwrap();
        let key = dir.join("munge.key");
        let socket = dir.join("munge.socket");
        let ok = Command::new("mungekey")
            .args(["--create", "--keyfile"])
            .arg(&key)
            .status()
            .unwrap();
        assert!(ok.success(), "mungekey failed");
        let mut cluster = Cluster {
            conf: dir.join("slurm.conf"),
            daemons: Vec::new(),
            dir: dir.clone(),
        };
        let log = |name: &str| std::fs::File::create(dir.join(name)).unwrap();
        cluster.daemons.push(
            Command::new("munged")
                .args(["--foreground", "--force", "--key-file"])
                .arg(&key)
                .arg("--socket")
                .arg(&socket)
                .arg("--pid-file")
                .arg(dir.join("munged.pid"))
                .arg("--seed-file")
                .arg(dir.join("munged.seed"))
                .arg("--log-file")
                .arg(dir.join("munged.log"))
                .stdout(log("munged.out"))
                .stderr(log("munged.err"))
                .spawn()
                .unwrap(),
        );
        let host = String::from_utf8(Command::new("hostname").arg("-s").output().unwrap().stdout)
            .unwrap()
            .trim()
            .to_string();
        let mem_mb = std::fs::read_to_string("/proc/meminfo")
            .unwrap()
            .lines()
            .find_map(|l| l.strip_prefix("MemTotal:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
            .unwrap()
            / 1024
            / 2;
        let cpus = std::thread::available_parallelism().map_or(2, std::num::NonZero::get);
        for sub in ["state", "spool"] {
            std::fs::create_dir_all(dir.join(sub)).unwrap();
        }
        let conf = format!(
            "ClusterName=kiwitest\nSlurmctldHost={host}(127.0.0.1)\nSlurmUser=root\nSlurmdUser=root\n\
             SlurmctldPort={}\nSlurmdPort={}\nAuthType=auth/munge\nCredType=cred/munge\n\
             AuthInfo=socket={}\nStateSaveLocation={}\nSlurmdSpoolDir={}\n\
             SlurmctldPidFile={}\nSlurmdPidFile={}\nSlurmctldLogFile={}\nSlurmdLogFile={}\n\
             ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\nMpiDefault=none\n\
             JobAcctGatherType=jobacct_gather/none\nAccountingStorageType=accounting_storage/none\n\
             JobCompType=jobcomp/none\nSchedulerType=sched/backfill\nSelectType=select/cons_tres\n\
             SelectTypeParameters=CR_CPU\nReturnToService=2\nMailProg=/bin/true\n\
             NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={mem_mb} State=UNKNOWN\n\
             PartitionName=kiwi Nodes={host} Default=YES MaxTime=INFINITE State=UP\n",
            free_port(),
            free_port(),
            socket.display(),
            dir.join("state").display(),
            dir.join("spool").display(),
            dir.join("slurmctld.pid").display(),
            dir.join("slurmd.pid").display(),
            dir.join("slurmctld.log").display(),
            dir.join("slurmd.log").display(),
        );
        std::fs::write(&cluster.conf, conf).unwrap();
        let start = Instant::now();
        while !socket.exists() {
            assert!(start.elapsed() < CLUSTER_START, "munged did not start");
            std::thread::sleep(Duration::from_millis(100));
        }
        for (program, args) in [
            ("slurmctld", vec!["-D", "-i", "-f"]),
            ("slurmd", vec!["-D", "-f"]),
        ] {
            cluster.daemons.push(
                Command::new(program)
                    .args(args)
                    .arg(&cluster.conf)
                    .env("SLURM_CONF", &cluster.conf)
                    .stdout(log(&format!("{program}.out")))
                    .stderr(log(&format!("{program}.err")))
                    .spawn()
                    .unwrap(),
            );
        }
        let start = Instant::now();
        loop {
            let out = cluster.cmd("sinfo").args(["-h", "-o", "%T"]).output();
            let state = out.map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string());
            if state.as_deref().is_ok_and(|s| s == "idle") {
                break;
            }
            assert!(
                start.elapsed() < CLUSTER_START,
                "the node never became idle ({state:?}); logs in {}:\n{}",
                cluster.dir.display(),
                std::fs::read_to_string(cluster.dir.join("slurmctld.log")).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(500));
        }
        cluster
    }

    /// A command with the test cluster's configuration.
    fn cmd(&self, program: &str) -> Command {
        let mut c = Command::new(program);
        c.env("SLURM_CONF", &self.conf);
        c
    }

    fn squeue(&self) -> String {
        let out = self
            .cmd("squeue")
            .args(["-h", "-o", "%i|%T|%r"])
            .output()
            .unwrap();
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    fn wait_until_empty(&self) {
        let start = Instant::now();
        while !self.squeue().trim().is_empty() {
            assert!(
                start.elapsed() < JOBS_END,
                "jobs still queued:\n{}",
                self.squeue()
            );
            std::thread::sleep(Duration::from_millis(500));
        }
    }
}

/// Four episodes (a survey that builds the maps, three short tabletop ones), one of them with
/// a corrupt stream: one frame of a lens is not an image.
fn session(dir: &Path) -> PathBuf {
    let toml = small_session(dir, 4);
    let frames = dir.join("episodes").join(CORRUPT).join("left/front/frames");
    let first = std::fs::read_dir(&frames)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .min()
        .unwrap();
    std::fs::write(first, b"not a png").unwrap();
    toml
}

/// Every result file of a session (stage folders and episode outputs; relative path → bytes,
/// the session's own path in text files replaced by `SESSION`), manifests left out (they hold
/// wall times).
fn results(root: &Path) -> Vec<(String, Vec<u8>)> {
    files(root)
        .into_iter()
        .filter(|(rel, _)| {
            rel.starts_with("work/") || rel.contains("/work/") || rel.contains("/out/")
        })
        .map(|(rel, bytes)| {
            // A failed episode's record names its files by path: compare them relative.
            let bytes = match String::from_utf8(bytes) {
                Ok(text) => text.replace(root.to_str().unwrap(), "SESSION").into_bytes(),
                Err(e) => e.into_bytes(),
            };
            (rel, bytes)
        })
        .collect()
}

fn kiwi(cluster: &Cluster, args: &[&str]) -> (bool, String, String) {
    let out = cluster.cmd(KIWI).args(args).output().unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn states(cluster: &Cluster, plan: &Path) -> serde_json::Value {
    let (ok, out, err) = kiwi(
        cluster,
        &[
            "batch",
            "status",
            "--json",
            "--plan",
            plan.to_str().unwrap(),
        ],
    );
    assert!(ok, "{err}");
    serde_json::from_str(&out).unwrap()
}

fn state_of<'a>(states: &'a serde_json::Value, episode: &str) -> &'a serde_json::Value {
    states
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["episode"] == episode)
        .unwrap()
}

#[test]
fn a_plan_runs_on_slurm_resumes_a_cancelled_task_and_matches_a_local_run() {
    let missing: Vec<&str> = [
        "munged",
        "mungekey",
        "slurmctld",
        "slurmd",
        "sbatch",
        "squeue",
    ]
    .into_iter()
    .filter(|p| !which(p))
    .collect();
    if !missing.is_empty() || !is_root() {
        eprintln!(
            "SKIPPED: the Slurm test needs root and {missing:?} (make deps installs slurm-wlm \
             and munge)"
        );
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let local = session(&tmp.path().join("local"));
    let cluster_root = tmp.path().join("cluster");
    copy_inputs(local.parent().unwrap(), &cluster_root);
    let toml = cluster_root.join("session.toml");
    let cluster = Cluster::start(&tmp.path().join("slurm"));

    // The plan, submitted; one task cancelled once its localization runs.
    let plan = cluster_root.join("batch");
    let (ok, out, err) = kiwi(
        &cluster,
        &[
            "batch",
            "plan",
            "--cpus",
            "1",
            "--session",
            toml.to_str().unwrap(),
            "--out",
            plan.to_str().unwrap(),
        ],
    );
    assert!(ok, "{err}");
    println!("{out}");
    let (ok, out, err) = kiwi(
        &cluster,
        &[
            "batch",
            "slurm",
            "--submit",
            "--plan",
            plan.to_str().unwrap(),
        ],
    );
    assert!(ok, "{err}");
    println!("{out}");
    // The reference, on this machine, while the cluster works.
    let reference = Command::new(KIWI)
        .args(["run", "--threads", "1", "--session"])
        .arg(&local)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();

    let start = Instant::now();
    while !localizing(&cluster_root, CANCELLED) {
        assert!(
            start.elapsed() < JOBS_END,
            "{CANCELLED} never localized:\n{}",
            cluster.squeue()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let job = state_of(&states(&cluster, &plan), CANCELLED)["job"]
        .as_str()
        .unwrap()
        .to_string();
    let ok = cluster.cmd("scancel").arg(&job).status().unwrap();
    assert!(ok.success());
    cluster.wait_until_empty();
    let reference = reference.wait_with_output().unwrap();
    assert_eq!(reference.status.code(), Some(2), "one episode is unusable");

    let s = states(&cluster, &plan);
    println!("{}", serde_json::to_string_pretty(&s).unwrap());
    assert_ne!(
        state_of(&s, CANCELLED)["state"],
        "done",
        "the cancelled task did not finish"
    );
    let corrupt = state_of(&s, CORRUPT);
    assert_eq!(corrupt["state"], "failed");
    assert!(
        corrupt["detail"].as_str().unwrap().contains("left/front"),
        "the corrupt episode's own error names its stream: {corrupt}"
    );
    for ep in ["ep000", "ep002"] {
        assert_eq!(state_of(&s, ep)["state"], "done", "{ep}");
    }
    let manifest = cluster_root.join("episodes/ep002/work/outputs/manifest.json");
    let before = std::fs::read(&manifest).unwrap();

    // Resubmitted: only the cancelled and the failed episode.
    let (ok, out, err) = kiwi(
        &cluster,
        &["batch", "resubmit", "--plan", plan.to_str().unwrap()],
    );
    assert!(ok, "{err}");
    println!("{out}");
    assert!(
        out.contains(CANCELLED) && out.contains(CORRUPT) && !out.contains("ep002"),
        "{out}"
    );
    cluster.wait_until_empty();
    let s = states(&cluster, &plan);
    assert_eq!(state_of(&s, CANCELLED)["state"], "done");
    assert_eq!(state_of(&s, CORRUPT)["state"], "failed");
    assert_eq!(
        std::fs::read(&manifest).unwrap(),
        before,
        "a finished episode was not re-run"
    );

    let (a, b) = (results(local.parent().unwrap()), results(&cluster_root));
    let names = |r: &[(String, Vec<u8>)]| r.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>();
    assert_eq!(names(&a), names(&b));
    for ((name, x), (_, y)) in a.iter().zip(&b) {
        assert!(
            x == y,
            "{name} differs between the local and the cluster run"
        );
    }
    drop(cluster);
}
