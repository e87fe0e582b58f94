"""The ``rgbdslam`` command line: parses options and calls library functions, nothing else.

Errors caused by input (``RgbdslamError``) are printed as one sentence and exit non-zero;
Ctrl-C exits with 130 after the library has saved what it finished.
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from rgbdslam.errors import InputError, RgbdslamError


class _Group(click.Group):
    """A click group that turns RgbdslamError into one line on stderr and an exit code."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except click.exceptions.NoArgsIsHelpError:
            raise
        except click.UsageError as e:  # a bad option or argument: one line, like every other error
            where = e.ctx.command_path if e.ctx is not None else "rgbdslam"
            click.secho(f"error: {e.format_message()} (see '{where} --help')", fg="red", err=True)
            sys.exit(2)
        except RgbdslamError as e:
            click.secho(f"error: {e}", fg="red", err=True)
            sys.exit(e.exit_code)
        except OSError as e:  # an output path that is a file, a folder without write access, a full disk
            what = f"{e.filename}: " if e.filename else ""
            click.secho(f"error: {what}{e.strerror or e}; check that the path is a writable folder "
                        f"(or readable file) and the disk is not full", fg="red", err=True)
            sys.exit(2)
        except KeyboardInterrupt:
            click.secho("interrupted: finished work was saved", fg="yellow", err=True)
            sys.exit(130)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="rgbdslam")
def main() -> None:
    """RGB-D visual SLAM: ORB + ISVD/ISLAM registration, DIF depth filter,
    sharpness-gated loop closure and a GTSAM pose graph initialised with MASAT."""


config_option = click.option(
    "--config", "-c", "config_path", default=None,
    help="YAML config file or the name of a preset shipped with rgbdslam (default, tum_fr1, ...).",
)
camera_option = click.option(
    "--camera", "camera_file", type=click.Path(path_type=Path), default=None, metavar="FILE",
    help="Camera file (YAML: fx, fy, cx, cy, size, distortion, depth_scale; see README 'Your own data'). "
         "Same as --set dataset.camera_file=FILE; wins over the camera a sequence or preset names.",
)


def load_cli_config(config_path, overrides, camera_file=None):
    """The config of a command: preset/file, --set overrides, then --camera."""
    from rgbdslam.config import load_config

    cfg = load_config(config_path, overrides)
    if camera_file is not None:
        cfg.dataset.camera_file = str(camera_file)
    return cfg


set_option = click.option(
    "--set", "-s", "overrides", multiple=True, metavar="SECTION.KEY=VALUE",
    help="Override one config value; repeatable.",
)


# ----------------------------------------------------------------------------- run / demo


@main.command()
@click.argument("sequences", nargs=-1, required=True, type=click.Path(path_type=Path), metavar="SEQUENCE...")
@config_option
@set_option
@camera_option
@click.option("--out", "-o", "out_dir", type=click.Path(path_type=Path), default=None,
              help="Output folder (default: runs/<sequence name>); with several sequences the folder "
                   "that holds one subfolder per sequence and summary.md/.csv (default: runs).")
@click.option("--no-map", is_flag=True, help="Skip map fusion at the end of the run.")
@click.option("--rerun", "rerun_spawn", is_flag=True, help="Stream the run to a Rerun viewer.")
@click.option("--rerun-save", type=click.Path(path_type=Path), default=None, help="Record the run to an .rrd file.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def run(sequences, config_path, overrides, camera_file, out_dir, no_map, rerun_spawn, rerun_save, quiet):
    """Run SLAM on SEQUENCE (a TUM, ETH3D, ICL-NUIM, 7-Scenes or PUT folder, a ROS 1/2 bag or a
    RealSense recording) and write trajectory.tum into --out.

    Several sequences run one after the other with the same config (camera "auto" is decided
    per sequence); a table of their results is printed and written to OUT/summary.md and .csv."""
    from rgbdslam.config import load_config
    from rgbdslam.batch import format_batch_table, run_sequences
    from rgbdslam.pipeline import run_sequence

    if len(sequences) > 1 and rerun_save is not None:
        raise click.UsageError("--rerun-save records one run: give a single SEQUENCE (or use --rerun)")
    cfg = load_cli_config(config_path, overrides, camera_file)
    if no_map:
        cfg.mapping.enabled = False
    if rerun_spawn:
        cfg.output.rerun = True
    if rerun_save is not None:
        cfg.output.rerun_save = str(rerun_save)
    if len(sequences) == 1:
        run_sequence(sequences[0], out_dir or Path("runs") / sequences[0].resolve().name, cfg, progress=not quiet)
        return
    out_root = out_dir or Path("runs")
    rows = run_sequences(list(sequences), out_root, cfg, progress=not quiet)
    click.echo(format_batch_table(rows))
    failed = [r for r in rows if r["status"] != "ok"]
    if failed:
        raise InputError(f"{len(failed)} of {len(rows)} sequences failed (first: {Path(failed[0]['sequence']).name}); "
                         f"see {out_root / 'summary.md'}")


@main.command()
@click.option("--out", "-o", "out_dir", type=click.Path(path_type=Path), default=Path("runs/demo"),
              help="Output folder for the demo sequence and the run.")
@click.option("--frames", default=100, show_default=True, help="Frames of the synthetic sequence.")
@config_option
@set_option
def demo(out_dir, frames, config_path, overrides):
    """Generate a synthetic sequence with exact ground truth, run SLAM on it and print its accuracy."""
    from rgbdslam.config import load_config
    from rgbdslam.pipeline import run_demo

    cfg = load_config(config_path, overrides)
    run_demo(out_dir, frames, cfg)


@main.command()
@config_option
@set_option
@click.option("--out", "-o", "out_dir", type=click.Path(path_type=Path), default=Path("runs/live"), show_default=True,
              help="Output folder of the run.")
@click.option("--record", "record_dir", type=click.Path(path_type=Path), default=None,
              help="Folder for the frames as they arrive, TUM layout (default: OUT/recording); "
                   "`rgbdslam run` on it repeats the session.")
@click.option("--playback", type=click.Path(path_type=Path), default=None,
              help="Take the frames from a RealSense recording (.bag/.db3) through the SDK's playback "
                   "instead of a camera.")
@click.option("--size", type=(int, int), default=(640, 480), show_default=True, metavar="W H",
              help="Stream size (colour and depth).")
@click.option("--fps", type=int, default=30, show_default=True, help="Frame rate of the streams.")
@click.option("--serial", default=None, help="Serial number of the camera to use (default: the first one).")
@click.option("--max-frames", type=int, default=None, help="Stop after this many frames.")
@click.option("--no-map", is_flag=True, help="Skip map fusion at the end of the run.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def live(config_path, overrides, out_dir, record_dir, playback, size, fps, serial, max_frames, no_map, quiet):
    """Run SLAM on a live RealSense camera (colour + depth aligned to colour; needs the
    [realsense] extra). Ctrl-C ends the session: the run then finishes and writes all its
    outputs (a second Ctrl-C stops at once, keeping what was finished)."""
    import signal

    from rgbdslam.datasets.realsense import RealSenseSequence
    from rgbdslam.pipeline import run_sequence
    from rgbdslam.ui import console

    cfg = load_cli_config(config_path, overrides)
    if no_map:
        cfg.mapping.enabled = False
    if max_frames is not None and max_frames < 1:
        raise click.UsageError("--max-frames must be at least 1")
    record_dir = record_dir or out_dir / "recording"
    seq = RealSenseSequence(record_dir, playback, size[0], size[1], fps, max_frames, serial)

    def first_interrupt(signum, frame):  # the first Ctrl-C ends the stream; the run then finishes normally
        console.print("[yellow]stopping: finishing the run (Ctrl-C again to stop at once)[/]")
        seq.stop()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    previous = signal.signal(signal.SIGINT, first_interrupt)
    try:
        run_sequence(seq, out_dir, cfg, progress=not quiet)
    finally:
        signal.signal(signal.SIGINT, previous)
        seq.close()
    console.print(f"frames recorded in {record_dir} (TUM layout): rgbdslam run {record_dir} repeats the session")


@main.command("config")
@config_option
@set_option
def show_config(config_path, overrides):
    """Print the effective configuration (defaults, preset, overrides) as YAML."""
    from rgbdslam.config import load_config

    click.echo(load_config(config_path, overrides).dump(), nl=False)


@main.command("info")
@click.argument("sequence", type=click.Path(path_type=Path))
@config_option
@set_option
@camera_option
def info(sequence, config_path, overrides, camera_file):
    """Describe SEQUENCE: reader, camera, frames, time span, ground truth."""
    from rgbdslam.datasets import describe_sequence

    click.echo(describe_sequence(sequence, load_cli_config(config_path, overrides, camera_file).dataset))


# ------------------------------------------------------------------ commands added by stages

@main.command()
@click.argument("gt", type=click.Path(path_type=Path))
@click.argument("est", type=click.Path(path_type=Path), nargs=-1, required=True)
@click.option("--align", type=click.Choice(["se3", "sim3", "none"]), default="se3", show_default=True,
              help="Alignment of EST onto GT before ATE (sim3 also fits a scale).")
@click.option("--delta", type=float, default=1.0, show_default=True, help="RPE pair distance.")
@click.option("--delta-unit", type=click.Choice(["f", "s", "m", "rad", "deg"]), default="f", show_default=True,
              help="Unit of --delta: frames, seconds, metres or radians/degrees along GT.")
@click.option("--max-difference", type=float, default=0.02, show_default=True,
              help="Max timestamp difference (s) for associating GT and EST poses.")
@click.option("--offset", type=float, default=0.0, show_default=True, help="Time offset (s) added to EST stamps.")
@click.option("--json", "json_path", type=click.Path(path_type=Path), default=None, help="Write the summary as JSON.")
@click.option("--plot-dir", type=click.Path(path_type=Path), default=None,
              help="Folder for the PNG plots (default: EST's folder, files named <EST stem>_*.png).")
@click.option("--no-plots", is_flag=True, help="Write no plots.")
def evaluate(gt, est, align, delta, delta_unit, max_difference, offset, json_path, plot_dir, no_plots):
    """ATE and RPE of trajectory EST against ground truth GT (TUM format, or a sequence folder
    with ground truth: TUM groundtruth.txt, 7-Scenes pose.txt files, ...); prints a table.

    Several ESTs are compared with the same settings: one table with a row each and
    comparison_topview.png (in --plot-dir, default the current folder) with all of them."""
    import tempfile

    from rgbdslam.evaluation.report import compare_and_print, evaluate_and_print

    opts = dict(align=align, delta=delta, delta_unit=delta_unit, max_difference=max_difference, offset=offset,
                json_path=json_path, plot_dir=plot_dir, plots=not no_plots)
    with tempfile.TemporaryDirectory(prefix="rgbdslam-gt-") as tmp:
        if gt.is_dir():  # a sequence folder: its own ground truth (7-Scenes pose.txt files, groundtruth.txt, ...)
            gt = _groundtruth_file(gt, Path(tmp))
        if len(est) == 1:
            evaluate_and_print(gt, est[0], **opts)
        else:
            compare_and_print(gt, list(est), **opts)


def _groundtruth_file(sequence: Path, tmp: Path) -> Path:
    """The ground truth of a sequence folder as a TUM file (its own file when it has one)."""
    from rgbdslam.datasets import open_sequence
    from rgbdslam.io.trajectory import write_tum

    gt = open_sequence(sequence).groundtruth()
    if gt is None:
        raise InputError(f"{sequence} is a folder without ground truth; give a TUM trajectory file as GT")
    path = tmp / f"{sequence.resolve().name}_groundtruth.tum"
    write_tum(gt, path)
    return path


@main.command()
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--frames", "-n", default=100, show_default=True, help="Number of frames (30 Hz).")
@click.option("--motion", type=click.Choice(["xyz", "rpy", "loop", "circle", "static"]), default="xyz",
              show_default=True, help="Camera motion; 'loop' returns to and revisits the start view.")
@click.option("--noise", is_flag=True, help="Kinect-like depth noise (sigma 1.2 mm + 1.9 mm (z-0.4)^2) and colour noise.")
@click.option("--dropout", type=float, default=0.0, show_default=True, help="Fraction of depth pixels lost in holes.")
@click.option("--drift", type=float, default=0.0, show_default=True,
              help="Systematic relative depth error: written depth = true depth * (1 + DRIFT).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the textures and the noise.")
@click.option("--camera", type=click.Choice(["ros_default", "fr1", "fr2", "fr3", "kinect1"]), default="ros_default",
              show_default=True, help="Camera model (its distortion is rendered).")
@click.option("--size", type=(int, int), default=(640, 480), show_default=True, metavar="W H", help="Image size.")
def synth(out, frames, motion, noise, dropout, drift, seed, camera, size):
    """Render a synthetic RGB-D sequence with exact ground truth into OUT (TUM layout)."""
    from rgbdslam.datasets.synthetic import synth_command

    synth_command(out, frames=frames, motion=motion, noise=noise, dropout=dropout, drift=drift, seed=seed,
                  camera=camera, width=size[0], height=size[1])


# ------------------------------------------------------------------------------- posegraph

_GRAPH_FORMATS = click.Choice(["auto", "g2o", "toro", "isam"])
_INIT_METHODS = ["masat", "weighted_masat", "odometry", "spanning_tree", "lago", "chordal"]
_optimizer_option = click.option(
    "--optimizer", type=click.Choice(["gtsam", "g2o", "lm"]), default="gtsam", show_default=True,
    help="gtsam: Gauss-Newton (Pose2 Logmap error, Expmap update); g2o: Gauss-Newton with g2o's SE(2) error "
         "and update (NumPy/SciPy; SE(2) only); lm: GTSAM Levenberg-Marquardt (robust from poor starts; "
         "not the MASAT paper's protocol).")


@main.group()
def posegraph() -> None:
    """Pose-graph files (g2o, TORO, iSAM): initial guesses (MASAT, ...), Gauss-Newton, the MASAT benchmark."""


@posegraph.command("info")
@click.argument("file", type=click.Path(path_type=Path))
@click.option("--format", "fmt", type=_GRAPH_FORMATS, default="auto", show_default=True, help="File format.")
def posegraph_info(file, fmt):
    """Describe the pose graph in FILE (kind, vertices, edges, duplicates)."""
    from rgbdslam.posegraph.graph_io import graph_info

    click.echo(graph_info(file, fmt))


@posegraph.command("init")
@click.argument("file", type=click.Path(path_type=Path))
@click.option("--method", type=click.Choice(_INIT_METHODS), default="masat", show_default=True,
              help="Initial guess (lago = GTSAM LAGO, SE(2); chordal = chordal relaxation: ours for SE(2), "
                   "GTSAM InitializePose3 for SE(3)).")
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True, help="Output g2o file.")
@click.option("--format", "fmt", type=_GRAPH_FORMATS, default="auto", show_default=True, help="Input format.")
def posegraph_init(file, method, out, fmt):
    """Compute an initial guess for the pose graph in FILE and write it (with the edges) as g2o."""
    from rgbdslam.posegraph.commands import initialize_file

    click.echo(initialize_file(file, method, out, fmt))


@posegraph.command("optimize")
@click.argument("file", type=click.Path(path_type=Path))
@click.option("--init", "init", type=click.Choice(_INIT_METHODS + ["file"]), default="masat", show_default=True,
              help="Initial guess ('file' = the file's own vertex estimates).")
@click.option("--out", "-o", type=click.Path(path_type=Path), default=None, help="Output g2o file.")
@click.option("--max-iter", default=50, show_default=True, help="Maximum iterations.")
@click.option("--tol", default=1e-6, show_default=True, help="Convergence threshold on the chi2 change.")
@click.option("--criterion", type=click.Choice(["absolute", "relative"]), default="relative", show_default=True,
              help="relative: |dchi2|/chi2 < tol (g2o's test); absolute: |dchi2| < tol.")
@click.option("--format", "fmt", type=_GRAPH_FORMATS, default="auto", show_default=True, help="Input format.")
@_optimizer_option
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def posegraph_optimize(file, init, out, max_iter, tol, criterion, fmt, optimizer, quiet):
    """Initialise and optimise the pose graph in FILE (Gauss-Newton, or --optimizer lm); print the chi2 report."""
    from rgbdslam.posegraph.commands import optimize_file

    click.echo(optimize_file(file, init=init, out=out, max_iter=max_iter, tol=tol, criterion=criterion, fmt=fmt,
                             progress=not quiet, optimizer=optimizer))


@posegraph.command("bench")
@click.option("--dataset", type=click.Choice(["m3500", "city10k", "m10000"]), default=None,
              help="Benchmark graph (required unless --merge-runs).")
@click.option("--noise", default="0.2,0.2,0.2", show_default=True,
              help="sx,sy,stheta (several separated by ';'), or 'all' for the MASAT paper's 8 levels.")
@click.option("--instances", default=50, show_default=True, help="Noisy instances per noise level.")
@click.option("--max-iter", default=50, show_default=True, help="Maximum iterations.")
@click.option("--workers", default=1, show_default=True, help="Parallel worker processes.")
@click.option("--seed", default=0, show_default=True, help="Seed of the noise.")
@click.option("--criterion", type=click.Choice(["absolute", "relative"]), default="relative", show_default=True,
              help="Convergence test of Tables 1/2: |dchi2|/chi2 < 1e-6 (relative, g2o's) or |dchi2| < 1e-6 "
                   "(absolute); the report shows the other one as Table 1b.")
@click.option("--methods", default="odometry,spanning_tree,masat,weighted_masat,lago,chordal,ground_truth",
              show_default=True,
              help="Comma-separated initial guesses to compare.")
@click.option("--out", "-o", "out_dir", type=click.Path(path_type=Path), default=None,
              help="Folder for runs.csv, table1.csv, table2.csv, report.md.")
@click.option("--data", "data_dir", type=click.Path(path_type=Path), default=None,
              help="Data folder holding posegraph/ (default: $RGBDSLAM_DATA).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.option("--timing-only", is_flag=True, help="Only time the initial guesses (best of 5) at each noise level.")
@click.option("--merge-runs", "merge", type=click.Path(path_type=Path), multiple=True,
              help="Instead of running: merge these runs.csv files (later rows replace earlier) into new tables.")
@click.option("--first-instance", default=0, show_default=True,
              help="Index of the first noisy instance (to add instances to an earlier run; see --merge-runs).")
@_optimizer_option
def posegraph_bench(dataset, noise, instances, max_iter, workers, seed, criterion, methods, out_dir, data_dir, quiet,
                    timing_only, merge, first_instance, optimizer):
    """The MASAT paper's protocol: noisy instances, initial guesses, Gauss-Newton; Tables 1 and 2."""
    from rgbdslam.posegraph.bench import bench_command

    click.echo(bench_command(dataset, noise, instances=instances, max_iter=max_iter, workers=workers, seed=seed,
                             criterion=criterion, methods=methods, out_dir=out_dir, data_dir=data_dir,
                             progress=not quiet, timing_only=timing_only, merge=merge,
                             first_instance=first_instance, optimizer=optimizer))


# ------------------------------------------------------------------------------- maps / viewer


@main.command()
@click.argument("run_dir", type=click.Path(path_type=Path))
@set_option
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def fuse(run_dir, overrides, quiet):
    """Fuse the map of a finished run folder into RUN_DIR/map: cloud.ply, mesh.ply, map2d.png/.yaml.

    Uses the run's config.yaml; --set mapping.KEY=VALUE changes it for this fusion."""
    from rgbdslam.mapping.fusion import fuse_command

    fuse_command(run_dir, overrides, progress=not quiet)


@main.command()
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--save", type=click.Path(path_type=Path), default=None,
              help="Write the recording here (default for a run folder: RUN_DIR/recording.rrd).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def view(path, save, quiet):
    """Open PATH (an .rrd recording or a run folder, recorded first) in the Rerun viewer."""
    from rgbdslam.viz.rerun_log import view as view_recording

    view_recording(path, save, progress=not quiet)


if __name__ == "__main__":  # pragma: no cover
    main()
