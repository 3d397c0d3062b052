//! `tools/slurm/canopy-frame.sh` through a real, single-node Slurm: `slurmctld` and `slurmd`
//! on loopback with a configuration written into a temporary directory (authentication
//! off: one machine, one user). Sponza rendered as 8 path-traced tiles by a job array and
//! assembled by a dependent job is the single-process image bit for bit. Skipped, saying
//! so, where Slurm is not installed or the test does not run as root (the daemons run as
//! the user they start as); `tools/slurm/README.md` says how to install it.

mod common;
use canopy::image::Image;
use common::*;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// The daemons of a test cluster, stopped on drop.
struct Cluster {
    dir: PathBuf,
}

impl Cluster {
    fn conf(&self) -> PathBuf {
        self.dir.join("slurm.conf")
    }

    fn start(dir: &Path) -> Option<Cluster> {
        let port = 20000 + std::process::id() % 20000;
        let d = dir.display();
        let conf = format!(
            "ClusterName=canopytest\nSlurmctldHost=localhost\nSlurmctldPort={port}\nSlurmdPort={}\n\
             AuthType=auth/none\nCredType=cred/none\nSlurmUser=root\nSlurmdUser=root\n\
             StateSaveLocation={d}/state\nSlurmdSpoolDir={d}/spool\n\
             SlurmctldPidFile={d}/slurmctld.pid\nSlurmdPidFile={d}/slurmd.pid\n\
             SlurmctldLogFile={d}/slurmctld.log\nSlurmdLogFile={d}/slurmd.log\n\
             ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\n\
             SelectType=select/cons_tres\nSelectTypeParameters=CR_Core_Memory\n\
             SchedulerType=sched/builtin\nReturnToService=2\nMpiDefault=none\n\
             JobAcctGatherType=jobacct_gather/none\n\
             NodeName=localhost CPUs=2 RealMemory=8000 State=UNKNOWN\n\
             PartitionName=debug Nodes=localhost Default=YES MaxTime=INFINITE State=UP\n",
            port + 1
        );
        for sub in ["state", "spool"] {
            std::fs::create_dir_all(dir.join(sub)).unwrap();
        }
        std::fs::write(dir.join("slurm.conf"), conf).unwrap();
        let cluster = Cluster {
            dir: dir.to_path_buf(),
        };
        let run = |prog: &str, args: &[&str]| {
            Command::new(prog)
                .args(args)
                .env("SLURM_CONF", cluster.conf())
                .status()
                .is_ok_and(|s| s.success())
        };
        if !run("slurmctld", &["-c"]) || !run("slurmd", &["-c", "-N", "localhost"]) {
            return None;
        }
        let up = Instant::now();
        while up.elapsed() < Duration::from_secs(60) {
            if cluster.slurm("sinfo", &["-h", "-o", "%T"]).trim() == "idle" {
                return Some(cluster);
            }
            std::thread::sleep(Duration::from_millis(500));
        }
        None
    }

    fn slurm(&self, prog: &str, args: &[&str]) -> String {
        let out = Command::new(prog)
            .args(args)
            .env("SLURM_CONF", self.conf())
            .output()
            .unwrap();
        String::from_utf8_lossy(&out.stdout).into_owned()
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        for pid in ["slurmd.pid", "slurmctld.pid"] {
            if let Ok(p) = std::fs::read_to_string(self.dir.join(pid)) {
                Command::new("kill").arg(p.trim()).status().ok();
            }
        }
    }
}

fn installed(prog: &str) -> bool {
    Command::new("sh")
        .args(["-c", &format!("command -v {prog}")])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// Says the test skipped where a run's log shows it (straight to standard error: the test
/// harness would hold back `eprintln!`), and leaves a marker `.ci/run` reads: as root
/// with Slurm installed, a skip fails the run.
fn skipped(why: &str) {
    use std::io::Write;
    let line = format!("tests/slurm.rs SKIPPED: {why}\n");
    std::io::stderr().write_all(line.as_bytes()).ok();
    let marker = Path::new(env!("CARGO_TARGET_TMPDIR")).join("slurm-test-skipped");
    std::fs::write(marker, line).ok();
}

#[test]
fn sponza_as_eight_slurm_tiles_is_the_single_process_image() {
    let marker = Path::new(env!("CARGO_TARGET_TMPDIR")).join("slurm-test-skipped");
    std::fs::remove_file(marker).ok();
    let root = Command::new("id").arg("-u").output().unwrap().stdout == b"0\n";
    if !["slurmctld", "slurmd", "sbatch"]
        .iter()
        .all(|p| installed(p))
        || !root
    {
        skipped("Slurm is not installed or this is not root (see tools/slurm/README.md)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let Some(cluster) = Cluster::start(&dir.path().join("slurm")) else {
        panic!(
            "the test cluster did not come up: see its logs in {}",
            dir.path().display()
        );
    };
    let arc = dir.path().join("sponza.canopy");
    convert(&scene("sponza.glb"), &arc, None);
    let out = dir.path().join("frame.exr");
    let size = [
        "--width", "96", "--height", "64", "--spp", "2", "--seed", "5",
    ];
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/slurm/canopy-frame.sh");
    let mut args = vec![
        s(&script),
        s(&arc),
        s(&out),
        "--tiles",
        "8",
        "--mem-budget",
        "256MiB",
    ];
    args.extend(size);
    let submit = Command::new("bash")
        .args(&args)
        .env("SLURM_CONF", cluster.conf())
        .env("CANOPY", env!("CARGO_BIN_EXE_canopy"))
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&submit.stdout);
    assert!(
        submit.status.success(),
        "{said}{}",
        String::from_utf8_lossy(&submit.stderr)
    );
    assert!(
        said.contains("tiles: job") && said.contains("assembly: job"),
        "{said}"
    );
    let start = Instant::now();
    while cluster.slurm("squeue", &["-h"]).trim() != "" {
        assert!(
            start.elapsed() < Duration::from_secs(600),
            "the jobs did not finish"
        );
        std::thread::sleep(Duration::from_millis(500));
    }
    let log = std::fs::read_to_string(dir.path().join("frame.exr.tiles/assemble.log"));
    assert!(out.exists(), "no frame; assembly log: {log:?}");
    let single = dir.path().join("single.exr");
    let mut one = vec!["--quiet", "render", s(&arc), "-o", s(&single)];
    one.extend(size);
    ok(&one);
    let (a, b) = (
        Image::read_exr(&out).unwrap(),
        Image::read_exr(&single).unwrap(),
    );
    assert!(
        a.pixels == b.pixels,
        "the assembled frame differs from the single render"
    );
}
