"""The ``rgbdslam`` command line: parses options and calls library functions, nothing else.

Errors caused by input (``RgbdslamError``) are printed as one sentence and exit non-zero;
Ctrl-C exits with 130 after the library has saved what it finished.
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from rgbdslam.errors import RgbdslamError


class _Group(click.Group):
    """A click group that turns RgbdslamError into one line on stderr and an exit code."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except RgbdslamError as e:
            click.secho(f"error: {e}", fg="red", err=True)
            sys.exit(e.exit_code)
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
    help="YAML config file or preset name from configs/ (e.g. tum_fr1).",
)
set_option = click.option(
    "--set", "-s", "overrides", multiple=True, metavar="SECTION.KEY=VALUE",
    help="Override one config value; repeatable.",
)


# ----------------------------------------------------------------------------- run / demo


@main.command()
@click.argument("sequence", type=click.Path(path_type=Path))
@config_option
@set_option
@click.option("--out", "-o", "out_dir", type=click.Path(path_type=Path), default=None,
              help="Output folder (default: runs/<sequence name>).")
@click.option("--no-map", is_flag=True, help="Skip map fusion at the end of the run.")
@click.option("--rerun", "rerun_spawn", is_flag=True, help="Stream the run to a Rerun viewer.")
@click.option("--rerun-save", type=click.Path(path_type=Path), default=None, help="Record the run to an .rrd file.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def run(sequence, config_path, overrides, out_dir, no_map, rerun_spawn, rerun_save, quiet):
    """Run SLAM on SEQUENCE (a TUM or PUT folder) and write trajectory.tum into --out."""
    from rgbdslam.config import load_config
    from rgbdslam.pipeline import run_sequence

    cfg = load_config(config_path, overrides)
    if no_map:
        cfg.mapping.enabled = False
    if rerun_spawn:
        cfg.output.rerun = True
    if rerun_save is not None:
        cfg.output.rerun_save = str(rerun_save)
    out_dir = out_dir or Path("runs") / sequence.resolve().name
    run_sequence(sequence, out_dir, cfg, progress=not quiet)


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


# ------------------------------------------------------------------ commands added by stages

@main.command()
@click.argument("gt", type=click.Path(path_type=Path))
@click.argument("est", type=click.Path(path_type=Path))
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
    """ATE and RPE of trajectory EST against ground truth GT (TUM format); prints a table."""
    from rgbdslam.evaluation.report import evaluate_and_print

    evaluate_and_print(gt, est, align=align, delta=delta, delta_unit=delta_unit, max_difference=max_difference,
                       offset=offset, json_path=json_path, plot_dir=plot_dir, plots=not no_plots)


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


if __name__ == "__main__":  # pragma: no cover
    main()
