"""The ``rgbdslam`` command line: parses options and calls library functions, nothing else.

Errors caused by input (``RgbdslamError``) are printed as one sentence and exit non-zero;
Ctrl-C exits with 130 after the library has saved what it finished.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import click

from rgbdslam.errors import InputError, RgbdslamError, bounded, exit_interrupted, one_line, was_interrupted


class _Group(click.Group):
    """A click group that turns RgbdslamError into one line on stderr and an exit code."""

    def invoke(self, ctx):
        try:
            with warnings.catch_warnings():
                # a last guard: inputs are checked where they are read, but no library's
                # RuntimeWarning (NumPy overflow, ...) is to reach the user between our lines
                warnings.simplefilter("ignore", RuntimeWarning)
                return super().invoke(ctx)
        except click.exceptions.NoArgsIsHelpError:
            raise
        except click.UsageError as e:  # a bad option or argument: one line, like every other error
            where = e.ctx.command_path if e.ctx is not None else "rgbdslam"
            click.secho(bounded(one_line(f"error: {e.format_message()} (see '{where} --help')")), fg="red", err=True)
            sys.exit(2)
        except RgbdslamError as e:
            click.secho(f"error: {e}", fg="red", err=True)
            sys.exit(e.exit_code)
        except OSError as e:  # an output path that is a file, a folder without write access, a full disk
            what = f"{e.filename}: " if e.filename else ""
            click.secho(bounded(one_line(f"error: {what}{e.strerror or e}; check that the path is a writable folder "
                                         f"(or readable file) and the disk is not full")), fg="red", err=True)
            sys.exit(2)
        except KeyboardInterrupt:
            exit_interrupted()
        except Exception:
            if was_interrupted():  # a library's error because Ctrl-C cut its import or work short
                exit_interrupted()
            raise

    def make_context(self, *args, **kwargs):
        try:
            return super().make_context(*args, **kwargs)
        except KeyboardInterrupt:  # while the options are parsed (click would say "Aborted!", exit 1)
            exit_interrupted()


class _NonEmptyPath(click.Path):
    """A path option or argument: '' is refused (``Path('')`` is the current folder, so ``--out ''``
    would write a whole run there)."""

    def convert(self, value, param, ctx):
        if isinstance(value, str) and not value.strip():
            self.fail("must not be empty; give a file or folder name", param, ctx)
        return super().convert(value, param, ctx)


PATH = _NonEmptyPath(path_type=Path)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="rgbdslam")
def main() -> None:
    """RGB-D visual SLAM: ORB + ISVD/ISLAM registration, DIF depth filter,
    sharpness-gated loop closure and a GTSAM pose graph initialised with MASAT."""


config_option = click.option(
    "--config", "-c", "config_path", default=None,
    help="YAML config file or the name of a preset shipped with rgbdslam (rgbdslam config --list-presets); "
         "without it the preset is chosen from the sequence's layout and camera.",
)
camera_option = click.option(
    "--camera", "camera_file", type=PATH, default=None, metavar="FILE",
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


def sequence_config(sequence, config_path, overrides, camera_file=None):
    """The config of a command on one SEQUENCE, as :func:`load_cli_config`; without --config, the
    preset that the sequence's layout and camera call for (:mod:`rgbdslam.datasets.preset_choice`).
    Returns the config and the choice (None with --config, or when no reader recognises SEQUENCE)."""
    from rgbdslam.datasets.preset_choice import choose_preset

    cfg = load_cli_config(config_path, overrides, camera_file)
    if config_path is not None:
        return cfg, None
    choice = choose_preset(sequence, cfg)
    if choice is None or choice.name == "default":  # the defaults are the default preset
        return cfg, choice
    return load_cli_config(choice.name, overrides, camera_file), choice


set_option = click.option(
    "--set", "-s", "overrides", multiple=True, metavar="SECTION.KEY=VALUE",
    help="Override one config value; repeatable.",
)


engine_options_list = [
    click.option("--engine", type=click.Choice(["local", "ray"]), default="local", show_default=True,
                 help="Where the jobs run: local (this process, or a process pool with --workers) or a Ray "
                      "cluster (pip install 'rgbdslam[distributed]').",),
    click.option("--workers", "-j", type=click.IntRange(min=1), default=1, show_default=True,
                 help="Parallel jobs: local worker processes, or the CPUs of a new local Ray cluster."),
    click.option("--address", default=None, metavar="ADDRESS",
                 help="With --engine ray: a running cluster (auto, HOST:6379 or ray://HOST:10001); inputs and "
                      "--out must be on storage every node sees at the same path."),
]


def engine_options(f):
    for opt in reversed(engine_options_list):
        f = opt(f)
    return f


def frame_options(f):
    """--first-frame / --stride / --max-frames: short for --set dataset.KEY=N (checked the same way)."""
    for name, key, text in (("--max-frames", "max_frames", "Track at most N frames (dataset.max_frames)."),
                            ("--stride", "stride", "Use every N-th frame (dataset.stride)."),
                            ("--first-frame", "first_frame", "Start at frame N, counted from 0 "
                                                             "(dataset.first_frame).")):
        f = click.option(name, key, type=int, default=None, metavar="N", help=text)(f)
    return f


def with_frame_options(overrides, first_frame, stride, max_frames) -> tuple[str, ...]:
    extra = [f"dataset.{k}={v}" for k, v in (("first_frame", first_frame), ("stride", stride),
                                             ("max_frames", max_frames)) if v is not None]
    return tuple(overrides) + tuple(extra)


# ----------------------------------------------------------------------------- run / demo


@main.command()
@click.argument("sequences", nargs=-1, required=True, type=PATH, metavar="SEQUENCE...")
@config_option
@set_option
@camera_option
@click.option("--out", "-o", "out_dir", type=PATH, default=None,
              help="Output folder (default: runs/<sequence name>); with several sequences the folder "
                   "that holds one subfolder per sequence and summary.md/.csv (default: runs).")
@click.option("--no-map", is_flag=True, help="Skip map fusion at the end of the run.")
@click.option("--rerun", "rerun_spawn", is_flag=True, help="Stream the run to a Rerun viewer.")
@click.option("--rerun-save", type=PATH, default=None, help="Record the run to an .rrd file.")
@frame_options
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.option("--map", "map_dir", type=click.Path(path_type=Path), default=None,
              help="A finished run's folder: relocalise in its map (map.npz), then extend it (saved in --out).")
@click.option("--localize", is_flag=True,
              help="With --map: only localise in the map (kept fixed); frames before the first "
                   "relocalisation are left out of trajectory.tum.")
@engine_options
def run(sequences, config_path, overrides, camera_file, out_dir, no_map, rerun_spawn, rerun_save, first_frame, stride,
        max_frames, quiet, map_dir, localize, engine, workers, address):
    """Run SLAM on SEQUENCE (a TUM, ETH3D, ICL-NUIM, 7-Scenes or PUT folder, a ROS 1/2 bag or a
    RealSense recording) and write trajectory.tum into --out.

    Without --config the preset is chosen from each sequence's layout and camera (KITTI -> kitti,
    TUM freiburg1/2/3 -> tum_fr1/2/3, PUT -> put_kinect1, else default) and printed with the reason;
    --config and --set win. Several sequences run one after the other (camera "auto" is decided
    per sequence); a table of their results is printed and written to OUT/summary.md and .csv.
    A run that loses most of its frames ends with one error line naming the likely fix (exit 3)."""
    from rgbdslam.batch import format_batch_table, run_sequences
    from rgbdslam.pipeline import run_sequence

    if len(sequences) > 1 and rerun_save is not None:
        raise click.UsageError("--rerun-save records one run: give a single SEQUENCE (or use --rerun)")
    if (map_dir is not None or localize) and len(sequences) > 1:
        raise click.UsageError("--map/--localize take a single SEQUENCE")
    if len(sequences) == 1 and (engine != "local" or workers != 1 or address is not None):
        raise click.UsageError("--engine/--workers/--address spread several sequences; give more than one SEQUENCE")
    configs, notes = [], []
    for sequence in sequences:  # without --config, each sequence's own preset
        cfg, choice = sequence_config(sequence, config_path, with_frame_options(overrides, first_frame, stride,
                                                                                max_frames), camera_file)
        if no_map:
            cfg.mapping.enabled = False
        if rerun_spawn:
            cfg.output.rerun = True
        if rerun_save is not None:
            cfg.output.rerun_save = str(rerun_save)
        configs.append(cfg)
        notes.append(choice.describe() if choice is not None else None)  # printed when the run starts
    if len(sequences) == 1:
        run_sequence(sequences[0], out_dir or Path("runs") / sequences[0].resolve().name, configs[0],
                     progress=not quiet, map_dir=map_dir, localize=localize, announce=notes[0])
        return
    out_root = out_dir or Path("runs")
    rows = run_sequences(list(sequences), out_root, configs, progress=not quiet, engine=engine, workers=workers,
                         address=address, notes=notes)
    click.echo(format_batch_table(rows))
    failed = [r for r in rows if r["status"] != "ok"]
    if failed:
        raise InputError(f"{len(failed)} of {len(rows)} sequences failed (first: {Path(failed[0]['sequence']).name}); "
                         f"see {out_root / 'summary.md'}")


@main.command()
@click.argument("sequences", nargs=-1, required=True, type=click.Path(path_type=Path), metavar="SEQUENCE...")
@click.option("--grid", "-g", "grid", multiple=True, metavar="SECTION.KEY=V1,V2,...",
              help="Values to sweep over; repeatable (every combination runs on every sequence).")
@config_option
@set_option
@click.option("--out", "-o", "out_dir", type=PATH, required=True,
              help="Folder for the cells' runs (cells/) and results.md/.csv/.png; a re-run keeps finished cells.")
@click.option("--map", "with_map", is_flag=True, help="Also fuse each cell's map (off: a sweep compares trajectories).")
@click.option("--quiet", "-q", is_flag=True, help="Only the table at the end.")
@engine_options
def sweep(sequences, grid, config_path, overrides, out_dir, with_map, quiet, engine, workers, address):
    """Run every combination of the --grid values on every SEQUENCE; one table of ATE, RPE and rate per cell.

    Example: rgbdslam sweep SEQ1 SEQ2 --grid registration.mp=2,4 --grid loop.enabled=true,false --out sweeps/a"""
    from rgbdslam.sweep import format_table, run_sweep
    from rgbdslam.ui import console

    quiet_before = console.quiet
    console.quiet = quiet or quiet_before
    try:
        res = run_sweep(list(sequences), list(grid), out_dir, config_path, tuple(overrides), engine=engine,
                        workers=workers, address=address, mapping=with_map)
    finally:
        console.quiet = quiet_before
    click.echo(format_table(res["rows"], res["columns"]))
    click.echo(f"{res['ran']} cell(s) run, {res['kept']} kept, {res['wall_s']:.1f} s ({res['engine']}); "
               f"{out_dir / 'results.md'}, results.csv, results.png")
    failed = [r for r in res["rows"] if r.get("status") != "ok"]
    if failed:
        raise InputError(f"{len(failed)} of {len(res['rows'])} cells failed (first: {failed[0]['status']})")


@main.command()
@click.option("--out", "-o", "out_dir", type=PATH, default=Path("runs/demo"),
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
@click.option("--out", "-o", "out_dir", type=PATH, default=Path("runs/live"), show_default=True,
              help="Output folder of the run.")
@click.option("--record", "record_dir", type=PATH, default=None,
              help="Folder for the frames as they arrive, TUM layout (default: OUT/recording); "
                   "`rgbdslam run` on it repeats the session.")
@click.option("--playback", type=PATH, default=None,
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
@click.option("--explain", is_flag=True,
              help="Print every key with its type, accepted range, default and a one-line description "
                   "(and the value here when the preset or --set changed it).")
@click.option("--list-presets", is_flag=True,
              help="List the presets shipped with rgbdslam (for -c NAME), what each is for and the layouts "
                   "`run` chooses it for without --config.")
def show_config(config_path, overrides, explain, list_presets):
    """Print the effective configuration (defaults, preset, overrides) as YAML."""
    from rgbdslam.config import load_config

    if list_presets:
        from rgbdslam.config_doc import preset_list

        click.echo(preset_list(), nl=False)
        return

    cfg = load_config(config_path, overrides)
    if explain:
        from rgbdslam.config_doc import explain as explain_config

        click.echo(explain_config(cfg), nl=False)
        return
    click.echo(cfg.dump(), nl=False)


@main.command("info")
@click.argument("sequence", type=PATH)
@config_option
@set_option
@camera_option
@frame_options
def info(sequence, config_path, overrides, camera_file, first_frame, stride, max_frames):
    """Describe SEQUENCE: reader, camera, frames, time span, ground truth, and the preset `run`
    chooses for it without --config."""
    from rgbdslam.datasets import describe_sequence

    cfg, choice = sequence_config(sequence, config_path, with_frame_options(overrides, first_frame, stride,
                                                                            max_frames), camera_file)
    click.echo(describe_sequence(sequence, cfg))
    if choice is not None:
        click.echo(f"preset      {choice.name}: {choice.reason} (what `run` uses without --config)")


@main.group()
def calibrate() -> None:
    """Measure a camera's calibration from a recording, without ground truth."""


@calibrate.command("depth-to-color")
@click.argument("sequence", type=PATH)
@click.option("--frames", type=click.IntRange(min=1), default=15, show_default=True,
              help="Frames sampled evenly over the sequence.")
@click.option("--focal", default="500:600:5", show_default=True, help="Colour focal lengths lo:hi:step (pixels).")
@click.option("--tx", default="-0.06:0.06:0.005", show_default=True,
              help="Depth-to-colour x translations lo:hi:step (m).")
@click.option("--ty", default="-0.03:0.03:0.005", show_default=True,
              help="Depth-to-colour y translations lo:hi:step (m).")
@click.option("--out", "out_file", type=click.Path(path_type=Path), default=None,
              help="Write a camera file (for run --camera) with the best values.")
@click.option("--check", multiple=True, type=PATH, metavar="CAMERA_FILE",
              help="Also score this camera file (e.g. a published calibration) on the same frames; repeatable.")
def calibrate_depth_to_color(sequence, frames, focal, tx, ty, out_file, check):
    """The colour focal length and depth-to-colour offset of SEQUENCE's unregistered depth: the
    grid setting that puts the depth images' outlines onto colour edges (docs/formats.md "7-Scenes")."""
    import tempfile

    from rgbdslam.calibration import depth_to_color as d2c

    grids = [d2c.grid(text, name) for text, name in ((focal, "--focal"), (tx, "--tx"), (ty, "--ty"))]
    with tempfile.TemporaryDirectory(prefix="rgbdslam_calibrate_") as tmp:
        seq = d2c.open_as_recorded(sequence, tmp)
        samples = d2c.samples_of(seq, frames)
    ranked = d2c.search(samples, seq.camera, *grids)
    recorded = d2c.score(samples, seq.camera.fx, seq.camera.cx, seq.camera.cy)
    click.echo(f"{len(ranked)} settings, {len(samples)} frames")
    click.echo(f"as recorded (colour = depth camera, no offset): score {recorded:.2f}")
    for s in ranked[:5]:
        click.echo(f"score {s.score:.2f}: colour focal {s.focal:g}, depth-to-colour t = ({s.tx:+.3f}, {s.ty:+.3f}, 0) m")
    for path in check:
        value, what = d2c.score_camera_file(samples, path)
        click.echo(f"score {value:.2f}: {path} ({what})")
    if out_file is not None:
        command = f"rgbdslam calibrate depth-to-color {sequence} --frames {frames} --focal {focal} --tx {tx} --ty {ty}"
        d2c.write_camera_file(out_file, seq, ranked[0], recorded, command)
        click.echo(f"wrote {out_file}")


@calibrate.command("stereo-offset")
@click.argument("sequence", type=PATH)
@click.option("--frames", type=click.IntRange(min=2), default=50, show_default=True,
              help="The first this many frames give the frame pairs.")
@click.option("--max-gap", type=click.IntRange(min=1), default=5, show_default=True,
              help="Frame pairs (i, i+g) for g = 1 .. this.")
@config_option
@set_option
def calibrate_stereo_offset(sequence, frames, max_gap, config_path, overrides):
    """The disparity offset (px) of SEQUENCE's stereo rig, without ground truth: one offset shared by
    all frame pairs, fitted with their motions on stereo reprojection residuals (docs/stereo.md
    "Disparity offset"). Prints the stereo.disparity_offset to run with: the configured one plus the
    fitted offset when that is more than two standard errors from 0."""
    from rgbdslam.datasets import open_sequence
    from rgbdslam.stereo.offset import estimate_disparity_offset

    cfg, _ = sequence_config(sequence, config_path, overrides)
    seq = open_sequence(sequence, cfg)
    if getattr(seq, "rig", None) is None:
        raise click.ClickException(f"{sequence} is not a stereo sequence (no right images): no disparity to calibrate")
    fit = estimate_disparity_offset(seq, cfg, range(min(frames, len(seq))), max_gap)
    if fit is None:
        raise click.ClickException(f"no frame pair of {sequence} has enough matched stereo points to fit an offset")
    click.echo(f"{fit.pairs} frame pairs, {fit.inliers} of {fit.residuals} residuals inliers")
    click.echo(f"disparity offset {fit.delta:+.3f} +- {fit.se:.3f} px on top of the configured "
               f"{cfg.stereo.disparity_offset:+.3f}")
    if fit.significant:
        click.echo(f"--set stereo.disparity_offset={cfg.stereo.disparity_offset + fit.delta:.3f}")
    else:
        click.echo(f"within two standard errors of 0: keep stereo.disparity_offset={cfg.stereo.disparity_offset:.3f}")


@calibrate.command("rolling-shutter")
@click.argument("sequence", type=PATH)
@click.option("--values", "--readouts", "values", default="0,0.005,0.01,0.015,0.02,0.025,0.03", show_default=True,
              help="Candidate values, comma-separated (readout times in seconds).")
@click.option("--key", default="features.rolling_shutter", show_default=True,
              help="The config key the values are for.")
@click.option("--camera-key", default=None, metavar="KEY[,KEY]",
              help="Camera-file keys the values are for instead (e.g. fx,fy), with --set dataset.camera_file=FILE.")
@click.option("--work", type=click.Path(path_type=Path), default=None,
              help="Folder for the runs (one per value; default a new temporary folder, kept).")
@config_option
@set_option
def calibrate_rolling_shutter(sequence, values, key, camera_key, work, config_path, overrides):
    """The rolling-shutter readout (or another value) at which SEQUENCE's odometry agrees best with
    its loop closures: one full run per value, no ground truth used (docs/slam.md "Rolling shutter")."""
    import tempfile

    from rgbdslam.calibration import rolling_shutter as rs

    try:
        candidates = [float(v) for v in values.split(",")]
    except ValueError:
        raise click.BadParameter(f"'{values}' is not comma-separated numbers", param_hint="--values") from None
    what = camera_key or key
    work = work or Path(tempfile.mkdtemp(prefix="rgbdslam_calibrate_rs_"))
    click.echo(f"runs in {work}")
    found = rs.calibrate(sequence, candidates, work, list(overrides), key=key,
                         camera_keys=camera_key.split(",") if camera_key else None,
                         config=lambda sets: sequence_config(sequence, config_path, sets)[0],
                         report=lambda c: click.echo(c.line(what)))
    best = rs.best(found)
    if best is None:
        click.echo("no run closed a loop: nothing to judge the values by")
    else:
        click.echo(f"smallest loop/odometry rotation discrepancy at {what} = {best.value:g}")


# ------------------------------------------------------------------ commands added by stages

@main.command()
@click.argument("gt", type=PATH)
@click.argument("est", type=PATH, nargs=-1, required=True)
@click.option("--align", type=click.Choice(["se3", "sim3", "none"]), default="se3", show_default=True,
              help="Alignment of EST onto GT before ATE (sim3 also fits a scale).")
@click.option("--delta", type=float, default=1.0, show_default=True, help="RPE pair distance.")
@click.option("--delta-unit", type=click.Choice(["f", "s", "m", "rad", "deg"]), default="f", show_default=True,
              help="Unit of --delta: frames, seconds, metres or radians/degrees along GT.")
@click.option("--max-difference", type=float, default=0.02, show_default=True,
              help="Max timestamp difference (s) for associating GT and EST poses.")
@click.option("--offset", type=float, default=0.0, show_default=True, help="Time offset (s) added to EST stamps.")
@click.option("--json", "json_path", type=PATH, default=None, help="Write the summary as JSON.")
@click.option("--plot-dir", type=PATH, default=None,
              help="Write PNG plots into this folder (none without it): ate_topview.png, ate_over_time.png, "
                   "rpe_over_time.png; with several EST each one's plots are prefixed with its short name "
                   "(e.g. runA_trajectory_ate_topview.png) and comparison_topview.png overlays them all.")
@click.option("--no-plots", is_flag=True, hidden=True, help="No effect: plots are written only with --plot-dir.")
def evaluate(gt, est, align, delta, delta_unit, max_difference, offset, json_path, plot_dir, no_plots):
    """ATE and RPE of trajectory EST against ground truth GT (TUM format, or a sequence folder
    with ground truth: TUM groundtruth.txt, 7-Scenes pose.txt files, ...); prints a table.

    Several ESTs are compared with the same settings: one table with a row each (and, with
    --plot-dir, comparison_topview.png with all of them)."""
    import tempfile

    from rgbdslam.evaluation.report import compare_and_print, evaluate_and_print

    opts = dict(align=align, delta=delta, delta_unit=delta_unit, max_difference=max_difference, offset=offset,
                json_path=json_path, plot_dir=plot_dir, plots=plot_dir is not None)
    with tempfile.TemporaryDirectory(prefix="rgbdslam-gt-") as tmp:
        if gt.is_dir():  # a sequence folder: its own ground truth (7-Scenes pose.txt files, groundtruth.txt, ...)
            gt = _groundtruth_file(gt, Path(tmp))
        elif gt.name.endswith(".gt.freiburg"):  # ICL-NUIM's own file: its conventions, as its reader applies them
            gt = _icl_groundtruth_file(gt, Path(tmp))
        if len(est) == 1:
            evaluate_and_print(gt, est[0], **opts)
        else:
            compare_and_print(gt, list(est), **opts)


def _groundtruth_file(sequence: Path, tmp: Path) -> Path:
    """The ground truth of a sequence folder as a TUM file (its own file when it has one)."""
    from rgbdslam.datasets import open_sequence
    from rgbdslam.io.trajectory import write_tum

    seq = open_sequence(sequence)
    gt = seq.groundtruth()
    if gt is None:
        raise InputError(f"{sequence} is a folder without ground truth; give a TUM trajectory file as GT")
    if seq.groundtruth_convention:
        click.echo(f"ground truth: {seq.groundtruth_convention}")
    path = tmp / f"{sequence.resolve().name}_groundtruth.tum"
    write_tum(gt, path)
    return path


def _icl_groundtruth_file(path: Path, tmp: Path) -> Path:
    """An ICL-NUIM ``*.gt.freiburg`` converted as the ICL-NUIM reader reads it, as a TUM file."""
    from rgbdslam.datasets.icl import convention, read_groundtruth
    from rgbdslam.io.trajectory import write_tum

    out = tmp / f"{path.name}.tum"
    write_tum(read_groundtruth(path), out)
    click.echo(f"ground truth: {convention(path)}")
    return out


@main.command()
@click.argument("out", type=PATH)
@click.option("--frames", "-n", default=100, show_default=True, help="Number of frames (30 Hz; --motion highway 10 Hz).")
@click.option("--motion", type=click.Choice(["xyz", "rpy", "loop", "circle", "static", "figure8", "revisit", "orbit",
                                             "highway"]),
              default="xyz", show_default=True,
              help="Camera motion; 'loop' returns to and revisits the start view; 'figure8' a fast figure eight "
                   "(~1 m/s, ~75 deg/s) with motion blur; 'revisit' maps a place, leaves, comes back to the same view; "
                   "'orbit' a slow orbit around a near, textured figure in a bare hall whose few textured door and window "
                   "frames lie 6-10 m away, depth to 10 m (as TUM fr3/teddy); "
                   "'highway' (--stereo only) a car at 25-30 m/s, 10 Hz, on a road with far structure.")
@click.option("--noise", is_flag=True, help="Kinect-like depth noise (sigma 1.2 mm + 1.9 mm (z-0.4)^2) and colour noise.")
@click.option("--dropout", type=float, default=0.0, show_default=True, help="Fraction of depth pixels lost in holes.")
@click.option("--drift", type=float, default=0.0, show_default=True,
              help="Systematic relative depth error: written depth = true depth * (1 + DRIFT).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the textures and the noise.")
@click.option("--camera", type=click.Choice(["ros_default", "fr1", "fr2", "fr3", "kinect1"]), default="ros_default",
              show_default=True, help="Camera model (its distortion is rendered).")
@click.option("--size", type=(int, int), default=(640, 480), show_default=True, metavar="W H", help="Image size.")
@click.option("--phase", type=float, default=0.0, show_default=True,
              help="Start further along the motion's path by this fraction (loop: 0.5 = the other side of the room).")
@click.option("--time-offset", type=float, default=0.0, show_default=True,
              help="Seconds added to every time stamp (a second session of the same scene).")
@click.option("--depth-delay", type=float, default=0.0, show_default=True, metavar="SECONDS",
              help="Depth images taken this long after the colour ones (negative: before), as TUM's freiburg1 "
                   "Kinect does (0-14 ms): depth rendered at the later pose, depth.txt stamped with it.")
@click.option("--stereo", "baseline", type=float, default=None, metavar="BASELINE",
              help="Render a grey stereo pair per frame instead, the right camera BASELINE metres to the right "
                   "(same scene and trajectory as the RGB-D sequence of the same options).")
@click.option("--layout", type=click.Choice(["kitti", "euroc"]), default="kitti", show_default=True,
              help="With --stereo: KITTI odometry or EuRoC/ASL folder layout.")
@click.option("--blur", type=float, default=None, metavar="MS",
              help="Motion blur: exposure time in ms (0 = sharp, at most 33.3). Default: 16 for figure8, 0 otherwise.")
def synth(out, frames, motion, noise, dropout, drift, seed, camera, size, phase, time_offset, depth_delay, baseline,
          layout, blur):
    """Render a synthetic RGB-D sequence with exact ground truth into OUT (TUM layout), or with
    --stereo a stereo sequence (KITTI or EuRoC layout)."""
    if motion == "highway" and baseline is None:
        raise InputError("--motion highway is a stereo scene; add --stereo BASELINE (KITTI: --stereo 0.54 --size 1241 376)")
    if baseline is not None:
        from rgbdslam.datasets.synthetic_stereo import synth_stereo_command

        if dropout or drift:
            raise InputError("--dropout and --drift simulate an RGB-D depth sensor; a --stereo sequence has no depth "
                             "images (leave them out)")
        if phase or time_offset or depth_delay:
            raise InputError("--phase, --time-offset and --depth-delay are for RGB-D sequences; leave them out with "
                             "--stereo")
        synth_stereo_command(out, baseline=baseline, layout=layout, frames=frames, motion=motion, noise=noise,
                             seed=seed, camera=camera, width=size[0], height=size[1], blur=blur)
        return
    from rgbdslam.datasets.synthetic import synth_command

    synth_command(out, frames=frames, motion=motion, noise=noise, dropout=dropout, drift=drift, seed=seed,
                  camera=camera, width=size[0], height=size[1], phase=phase, time_offset=time_offset, blur=blur, depth_delay=depth_delay)


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
@click.argument("file", type=PATH)
@click.option("--format", "fmt", type=_GRAPH_FORMATS, default="auto", show_default=True, help="File format.")
def posegraph_info(file, fmt):
    """Describe the pose graph in FILE (kind, vertices, edges, duplicates)."""
    from rgbdslam.posegraph.graph_io import graph_info

    click.echo(graph_info(file, fmt))


@posegraph.command("init")
@click.argument("file", type=PATH)
@click.option("--method", type=click.Choice(_INIT_METHODS), default="masat", show_default=True,
              help="Initial guess (lago = GTSAM LAGO, SE(2); chordal = chordal relaxation: ours for SE(2), "
                   "GTSAM InitializePose3 for SE(3)).")
@click.option("--out", "-o", type=PATH, required=True, help="Output g2o file.")
@click.option("--format", "fmt", type=_GRAPH_FORMATS, default="auto", show_default=True, help="Input format.")
def posegraph_init(file, method, out, fmt):
    """Compute an initial guess for the pose graph in FILE and write it (with the edges) as g2o."""
    from rgbdslam.posegraph.commands import initialize_file

    click.echo(initialize_file(file, method, out, fmt))


@posegraph.command("optimize")
@click.argument("file", type=PATH)
@click.option("--init", "init", type=click.Choice(_INIT_METHODS + ["file"]), default="masat", show_default=True,
              help="Initial guess ('file' = the file's own vertex estimates).")
@click.option("--out", "-o", type=PATH, default=None, help="Output g2o file.")
@click.option("--max-iter", default=50, show_default=True, help="Maximum iterations.")
@click.option("--tol", default=1e-6, show_default=True, help="Convergence threshold on the chi2 change.")
@click.option("--criterion", type=click.Choice(["absolute", "relative"]), default="relative", show_default=True,
              help="relative: |dchi2| <= tol * chi2 (g2o's test, scale-free), or chi2 down to the level "
                   "floating-point rounding alone gives the graph (an exact fit); absolute: |dchi2| < tol.")
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
@click.option("--workers", default=1, show_default=True,
              help="Parallel workers: local processes, or the CPUs of a new local Ray cluster.")
@click.option("--engine", type=click.Choice(["local", "ray"]), default="local", show_default=True,
              help="Where the instances run: local processes or a Ray cluster (pip install 'rgbdslam[distributed]').")
@click.option("--address", default=None, metavar="ADDRESS",
              help="With --engine ray: a running cluster (auto, HOST:6379 or ray://HOST:10001).")
@click.option("--seed", default=0, show_default=True, help="Seed of the noise.")
@click.option("--criterion", type=click.Choice(["absolute", "relative"]), default="relative", show_default=True,
              help="Convergence test of Tables 1/2: |dchi2|/chi2 < 1e-6 (relative, g2o's) or |dchi2| < 1e-6 "
                   "(absolute); the report shows the other one as Table 1b.")
@click.option("--methods", default="odometry,spanning_tree,masat,weighted_masat,lago,chordal,ground_truth",
              show_default=True,
              help="Comma-separated initial guesses to compare.")
@click.option("--out", "-o", "out_dir", type=PATH, default=None,
              help="Folder for runs.csv, table1.csv, table2.csv, report.md.")
@click.option("--data", "data_dir", type=PATH, default=None,
              help="Data folder holding posegraph/ (default: $RGBDSLAM_DATA).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.option("--timing-only", is_flag=True, help="Only time the initial guesses (best of 5) at each noise level.")
@click.option("--merge-runs", "merge", type=PATH, multiple=True,
              help="Instead of running: merge these runs.csv files (later rows replace earlier) into new tables.")
@click.option("--first-instance", default=0, show_default=True,
              help="Index of the first noisy instance (to add instances to an earlier run; see --merge-runs).")
@_optimizer_option
def posegraph_bench(dataset, noise, instances, max_iter, workers, engine, address, seed, criterion, methods, out_dir,
                    data_dir, quiet, timing_only, merge, first_instance, optimizer):
    """The MASAT paper's protocol: noisy instances, initial guesses, Gauss-Newton; Tables 1 and 2."""
    from rgbdslam.posegraph.bench import bench_command

    click.echo(bench_command(dataset, noise, instances=instances, max_iter=max_iter, workers=workers, seed=seed,
                             criterion=criterion, methods=methods, out_dir=out_dir, data_dir=data_dir,
                             progress=not quiet, timing_only=timing_only, merge=merge,
                             first_instance=first_instance, optimizer=optimizer, engine=engine, address=address))


# ------------------------------------------------------------------------------- maps / viewer


@main.command()
@click.argument("run_dir", type=PATH)
@set_option
@click.option("--render", is_flag=True,
              help="Also render PNG previews without a display: RUN_DIR/map/cloud.png and mesh.png.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def fuse(run_dir, overrides, render, quiet):
    """Fuse the map of a finished run folder into RUN_DIR/map: cloud.ply, mesh.ply, map2d.png/.yaml.

    Uses the run's config.yaml; --set mapping.KEY=VALUE changes it for this fusion."""
    from rgbdslam.mapping.fusion import fuse_command
    from rgbdslam.viz.render import render_run

    fuse_command(run_dir, overrides, progress=not quiet, render=render_run if render else None)


def _export_help() -> str:
    from rgbdslam.export import FORMATS

    return "Format(s) to write; repeatable or comma-separated, 'all' for every one: " + "; ".join(
        f"{k} = {v[2]}" for k, v in FORMATS.items()) + "."


@main.command()
@click.argument("run_dir", type=PATH)
@click.option("--format", "-f", "formats", multiple=True, required=True, metavar="FORMAT[,FORMAT...]",
              help=_export_help())
@click.option("--out", "-o", "out_dir", type=PATH, default=None,
              help="Output folder (default: RUN_DIR/export).")
@click.option("--max-points", default=100_000, show_default=True,
              help="Points in the COLMAP points3D.txt / nerfstudio sparse_pc.ply (the map's cloud, subsampled).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def export(run_dir, formats, out_dir, max_points, quiet):
    """Write a finished run (RUN_DIR) in formats other tools read: trajectories (TUM, KITTI,
    EuRoC, evo), COLMAP and nerfstudio models of the keyframes, the map as PCD/OBJ/GLB."""
    from rgbdslam.export import export_run, parse_formats

    written = export_run(run_dir, parse_formats(formats), out_dir, max_points=max_points, progress=not quiet)
    for name, paths in written.items():
        click.echo(f"{name}: " + ", ".join(str(p) for p in paths))


@main.command()
@click.argument("path", type=PATH)
@click.option("--save", type=PATH, default=None,
              help="Write the recording here (default for a run folder: RUN_DIR/recording.rrd).")
@click.option("--web", is_flag=True,
              help="Serve Rerun's web viewer (for a machine without a display) and print the address to open.")
@click.option("--bind", default="127.0.0.1", show_default=True,
              help="With --web: the address to serve on (0.0.0.0 = every network interface).")
@click.option("--web-port", default=9090, show_default=True, help="With --web: port of the viewer page.")
@click.option("--grpc-port", default=9876, show_default=True, help="With --web: port the recording is served on.")
@click.option("--serve-for", type=float, default=None, metavar="SECONDS",
              help="With --web: stop serving after this many seconds (default: until Ctrl-C).")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def view(path, save, web, bind, web_port, grpc_port, serve_for, quiet):
    """Open PATH (an .rrd recording or a run folder, recorded first) in the Rerun viewer."""
    from rgbdslam.viz.rerun_log import view as view_recording

    view_recording(path, save, progress=not quiet, web=web, bind=bind, web_port=web_port, grpc_port=grpc_port,
                   serve_for=serve_for)


if __name__ == "__main__":  # pragma: no cover
    main()
