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

    /// Runs a script of `tools/slurm/` with `args` against this cluster and waits until its
    /// jobs are done; returns what the script printed.
    fn run_script(&self, args: &[&str]) -> String {
        let submit = Command::new("bash")
            .args(args)
            .env("SLURM_CONF", self.conf())
            .env("CANOPY", env!("CARGO_BIN_EXE_canopy"))
            .output()
            .unwrap();
        let said = String::from_utf8_lossy(&submit.stdout).into_owned();
        let err = String::from_utf8_lossy(&submit.stderr);
        assert!(submit.status.success(), "{said}{err}");
        let start = Instant::now();
        while self.slurm("squeue", &["-h"]).trim() != "" {
            assert!(
                start.elapsed() < Duration::from_secs(600),
                "the jobs did not finish: {said}"
            );
            std::thread::sleep(Duration::from_millis(500));
        }
        said
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

#[test]
fn slurm_jobs_write_what_one_process_writes() {
    let marker = Path::new(env!("CARGO_TARGET_TMPDIR")).join("slurm-test-skipped");
    std::fs::remove_file(&marker).ok();
    let root = Command::new("id").arg("-u").output().unwrap().stdout == b"0\n";
    if !["slurmctld", "slurmd", "sbatch"]
        .iter()
        .all(|p| installed(p))
        || !root
    {
        skipped(
            &marker,
            "tests/slurm.rs",
            "Slurm is not installed or this is not root (see tools/slurm/README.md)",
        );
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
    let said = cluster.run_script(&args);
    assert!(
        said.contains("tiles: job") && said.contains("assembly: job"),
        "{said}"
    );
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
    // The cone integrator: a pre-pass job writes the stored light, every tile starts from
    // it, and the frame is assembled once they all succeeded.
    let cone_out = dir.path().join("cone.exr");
    let mut args = vec![s(&script), s(&arc), s(&cone_out), "--tiles", "2"];
    args.extend(size);
    args.extend(["--integrator", "cone"]);
    let said = cluster.run_script(&args);
    assert!(said.contains("pre-pass: job"), "{said}");
    let store = dir.path().join("cone.exr.tiles/light.store");
    assert!(store.exists(), "the pre-pass wrote no light store");
    assert!(all_finite(&Image::read_exr(&cone_out).unwrap()));
    let reread = dir.path().join("reread.exr");
    let mut one = vec!["--quiet", "render", s(&arc), "-o", s(&reread)];
    one.extend(size);
    one.extend(["--integrator", "cone", "--store-in", s(&store)]);
    ok(&one);
    // A conversion as a prepare job, a job array of its chunks and a join: the bytes one
    // process writes.
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/slurm/canopy-convert.sh");
    let staged = dir.path().join("staged.canopy");
    let budget = ["--mem-budget", "98MiB"];
    let bunny = scene("bunny.ply");
    let mut args = vec![s(&script), s(&staged), s(&bunny), "--concurrent", "2"];
    args.extend(budget);
    let said = cluster.run_script(&args);
    assert!(said.contains("prepare: job"), "{said}");
    let jobs = dir.path().join("staged.canopy.work/jobs");
    let log = |name: &str| std::fs::read_to_string(jobs.join(name)).unwrap_or_default();
    assert!(
        staged.exists(),
        "no archive; prepare: {} join: {}",
        log("prepare.log"),
        log("join.log")
    );
    assert!(
        log("prepare.log").contains("chunks: job"),
        "{}",
        log("prepare.log")
    );
    let single = dir.path().join("single.canopy");
    let mut one = vec!["--quiet", "convert", s(&bunny), "-o", s(&single)];
    one.extend(budget);
    ok(&one);
    assert!(
        std::fs::read(&staged).unwrap() == std::fs::read(&single).unwrap(),
        "the archive the jobs wrote differs from the single process's"
    );
    assert!(
        !dir.path().join("staged.canopy.work/state").exists(),
        "the join left its work files"
    );
}

/// The conversion script refuses bad arguments before it submits anything: each case exits
/// with status 2 and names what is wrong.
#[test]
fn the_slurm_convert_script_refuses_bad_arguments_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.canopy");
    let bunny = scene("bunny.ply");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/slurm/canopy-convert.sh");
    let missing = dir.path().join("none.ply");
    let cases: [(&str, Vec<&str>, &str); 5] = [
        ("no input", vec!["--mem-budget", "1GiB"], "no input files"),
        (
            "missing input",
            vec![s(&missing)],
            "none.ply: no such input file",
        ),
        (
            "-o",
            vec![s(&bunny), "-o", "y.canopy"],
            "-o is set by canopy-convert.sh",
        ),
        (
            "--chunk",
            vec![s(&bunny), "--chunk", "1"],
            "--chunk is set by",
        ),
        (
            "--concurrent 0",
            vec![s(&bunny), "--concurrent", "0"],
            "--concurrent K must be a positive whole number",
        ),
    ];
    for (what, extra, expect) in cases {
        let args = [&[s(&script), s(&out)][..], &extra].concat();
        script_refuses(what, &args, expect);
        assert!(
            !out.exists() && !dir.path().join("x.canopy.work").exists(),
            "{what}"
        );
    }
}

/// Runs a script of `tools/slurm/` with `args` (no Slurm needed) and checks it exits with
/// status 2 naming `expect`.
fn script_refuses(what: &str, args: &[&str], expect: &str) {
    let run = Command::new("bash")
        .args(args)
        .env("CANOPY", env!("CARGO_BIN_EXE_canopy"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(2), "{what}: {err}");
    assert!(err.contains(expect), "{what}: expected '{expect}' in {err}");
}

/// The script refuses bad arguments before it submits anything (no Slurm needed): each
/// case exits with status 2 and names what is wrong.
#[test]
fn the_slurm_script_refuses_bad_arguments_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("cbox.canopy");
    convert(&scene("cbox.glb"), &arc, None);
    let out = dir.path().join("frame.exr");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/slurm/canopy-frame.sh");
    let size = ["--width", "64", "--height", "48"];
    let missing = dir.path().join("none.canopy");
    let cases: [(&str, &Path, Vec<&str>, &str); 8] = [
        (
            "no --tiles",
            &arc,
            size.to_vec(),
            "--tiles N (a positive whole number) is required",
        ),
        (
            "--tiles 0",
            &arc,
            [&size[..], &["--tiles", "0"]].concat(),
            "--tiles N",
        ),
        (
            "no size",
            &arc,
            vec!["--tiles", "2"],
            "--width and --height are required",
        ),
        (
            "more tiles than rows",
            &arc,
            [&size[..], &["--tiles", "49"]].concat(),
            "more than the 48 rows",
        ),
        (
            "--crop",
            &arc,
            [&size[..], &["--tiles", "2", "--crop", "0,8,0,8"]].concat(),
            "--crop is set by canopy-frame.sh",
        ),
        (
            "--store-in",
            &arc,
            [&size[..], &["--tiles", "2", "--store-in", "x"]].concat(),
            "--store-in is set by canopy-frame.sh",
        ),
        (
            "--concurrent 0",
            &arc,
            [&size[..], &["--tiles", "2", "--concurrent", "0"]].concat(),
            "--concurrent K must be a positive whole number",
        ),
        (
            "no archive",
            &missing,
            [&size[..], &["--tiles", "2"]].concat(),
            "none.canopy: no such archive",
        ),
    ];
    for (what, archive, extra, expect) in cases {
        let args = [&[s(&script), s(archive), s(&out)][..], &extra].concat();
        script_refuses(what, &args, expect);
        assert!(
            !out.exists() && !dir.path().join("frame.exr.tiles").exists(),
            "{what}"
        );
    }
}
