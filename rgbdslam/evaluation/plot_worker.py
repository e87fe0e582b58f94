"""A run's evaluation plots, drawn in a process of their own.

Drawing the three plots of a run (``evaluation/plots.py``) costs ~0.5 s of CPU after the last
frame, and importing matplotlib with its fonts another ~0.6 s (2-core machine,
docs/benchmarks.md "Scale"). The process is started with the run, imports matplotlib and draws a
throw-away figure (font cache, Agg) while the frames are tracked, in a thread at a lower
priority (niceness + ``nice``, ``mapping.live_nice`` as the map process) so that tracking keeps its speed; after the
last frame its main thread, at the run's priority, draws the plots while the run waits for the map. The numbers (ATE, RPE) are computed by the run
itself: only the drawing is here.
"""

from __future__ import annotations

from pathlib import Path

from rgbdslam.io.worker import end, exit_now, follow_parent, in_niced_thread, receive, spawn_context, start


class PlotWorker:
    """The plot process seen from the run: :meth:`submit` a report once, :meth:`result` gives the
    paths of the written plots (its error raised here), :meth:`close` ends it (also unused)."""

    def __init__(self, nice: int = 10):
        ctx = spawn_context()
        self._jobs = ctx.Queue()
        self._results = ctx.Queue()
        self._proc = ctx.Process(target=_serve, name="rgbdslam-plots", daemon=True, args=(self._jobs, self._results, nice))
        start(self._proc)
        self.submitted = False

    def submit(self, report, plot_dir: str | Path, prefix: str = "") -> None:
        """Draw ``report``'s plots (:func:`rgbdslam.evaluation.report.write_plots`) into ``plot_dir``."""
        self._jobs.put((report, str(plot_dir), prefix))
        self.submitted = True

    def result(self) -> list[str]:
        """The written plots' paths, when they are written."""
        status, value = receive(self._results, self._proc, "plot process")
        self._proc.join(timeout=5)
        if status == "error":
            raise value
        return value

    def close(self) -> None:
        """End the process (without plots when none were submitted)."""
        end(self._proc, self._jobs)


def _warm_up() -> None:
    """What the first plot of a process pays besides drawing: the imports, the font cache, Agg."""
    import io

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    import rgbdslam.evaluation.report  # noqa: F401 - the drawing code and what it imports

    fig = Figure(figsize=(2, 2))
    ax = fig.add_subplot(1, 1, 1)
    ax.plot([0, 1], [0, 1], label="x")
    ax.legend()
    ax.set_title("warm-up")
    FigureCanvasAgg(fig)
    fig.savefig(io.BytesIO(), format="png", dpi=40, bbox_inches="tight")


def _serve(jobs, results, nice: int) -> None:
    """The plot process: warm up, draw the one report sent, send the paths (or the error), exit
    without the interpreter's teardown (the run does not wait for it)."""
    import signal

    follow_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the run's to handle: it stops us
    try:
        in_niced_thread(nice, _warm_up)  # while tracking: niced; the plots after it at the run's priority
        job = jobs.get()
        if job is not None:
            from rgbdslam.evaluation.report import write_plots

            report, plot_dir, prefix = job
            results.put(("ok", write_plots(report, plot_dir, prefix)))
    except BaseException as e:  # noqa: BLE001 - the run reports it
        from rgbdslam.errors import RgbdslamError

        results.put(("error", e if isinstance(e, RgbdslamError) else RuntimeError(f"{type(e).__name__}: {e}")))
    exit_now(results)
