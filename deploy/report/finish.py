"""The end of a supervised run, the same for `smana up` and `smana replay --run`: the report, the
terminal's summary and the exit status; and, while the run goes, a progress bar of the service
that ends it.

What went wrong (a service never ready or crash-looping, no path answered, a robot that did not
move, a scan lost in lockstep, a recorder that missed poses) heads report.md, ends the terminal
summary and makes the exit status 1. A report that cannot be written is one more warning: it never
hides the run's own outcome.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import sys
import threading
from pathlib import Path

log = logging.getLogger("smana.up")

REPLAY_SUMMARY = (
    "replay.json"  # services/replay/service.py writes it when it has sent its last scan
)


def finish(sup, run_dir, code: int, wall_time_s: float, prog: str = "smana up") -> int:
    """Write the report of `run_dir` (as the user named it: metrics.json and the summary say it
    so) from what `sup` (a finished `Supervisor`) saw, print its summary
    and return the exit status: 0 when the run did its job, 1 otherwise. A replayed dataset
    (`deploy.finish_with = "replay"`) is reported in its replay form (the dataset, its figures,
    the map's content; nothing against a simulated world)."""
    from smana.deploy.report.render import summary_lines
    from smana.deploy.report.write import write_report

    run_dir = Path(run_dir)
    warnings = sup.warnings()
    replay = None
    if sup.config.deploy.finish_with == "replay":
        code, warnings, replay = _replay_outcome(run_dir, code, warnings, prog)
    explored = any(m.service == "explorer" for m in sup.procs.values())
    try:
        path = write_report(
            run_dir,
            sup.service_config,
            replay=replay,
            warnings=warnings,
            explored=explored,
            ended=sup.ended,
            wall_time_s=wall_time_s,
        )
        # the terminal's summary is made from what metrics.json holds, as report.md's is
        metrics = json.loads((run_dir / "metrics.json").read_text())
        warnings = metrics.get("warnings", warnings)
        print(f"{prog}: report written to {path}", flush=True)
        summary = summary_lines(metrics, prog)
    except Exception as exc:  # a failed report must not hide the run's own outcome
        log.exception("writing the report failed: %s", exc)
        warnings = [*warnings, f"the report could not be written: {exc}"]
        summary = [f"{prog}: FAILED", f"  run directory  {run_dir}"]
        summary += [f"  warning: {w}" for w in warnings]
    print("\n".join(summary), flush=True)
    return 1 if warnings or code else 0


def _replay_outcome(run_dir: Path, code: int, warnings: list[str], prog: str):
    """(exit status, warnings, the replay's summary) of a supervised replay. A replay that
    finished its work (its summary written, every scan handled) and was only caught exiting is no
    failure: the supervisor kills a process whose liveliness token went before the process did."""
    if code != 0 and replay_completed(run_dir):
        print(f"{prog}: the replay completed; its exit was cut short", file=sys.stderr)
        code = 0
        warnings = [w for w in warnings if not w.startswith("replay exited with status")]
    path = run_dir / REPLAY_SUMMARY
    if not path.is_file():
        warnings = [*warnings, "the replay did not finish (no replay.json; see logs/replay.log)"]
        print(
            f"{prog}: no {path} (the replay did not finish); the report has no replay section",
            file=sys.stderr,
        )
        return code, warnings, {}
    return code, warnings, json.loads(path.read_text())


def replay_completed(run_dir: Path) -> bool:
    """The replay wrote its summary and handled every scan (nothing lost in lockstep)."""
    path = Path(run_dir) / REPLAY_SUMMARY
    if not path.is_file():
        return False
    s = json.loads(path.read_text())
    handled = s["published"] + s["empty"] + len(s["read_errors"])
    return handled == s["scans"] and not (s["mode"] == "lockstep" and s["lost"])


class RunProgress:
    """A bar of the service that ends the run (`deploy.finish_with`), when its status publishes
    `progress` as "done/total" (the replay: the scans it has sent): supervised services write to
    their log files, so this process draws it, from the statuses the supervisor follows. On a
    terminal only (common/progress.py); the supervisor's 10 s line and the logs are then written
    above the bar. Nothing is drawn for a service whose progress is not a count."""

    def __init__(self, sup):
        from smana.common import progress

        self.sup, self.progress = sup, progress
        self.key = (sup.config.general.robot, sup.config.deploy.finish_with)
        self.on = progress.enabled()
        self.bar = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._follow, name="run-progress", daemon=True)
        self._logs = progress.logs_around_bar()

    def __enter__(self):
        self._logs.__enter__()
        if self.on:
            plain = self.sup.print_progress

            def print_progress(elapsed_s: float) -> None:
                buf = io.StringIO()
                with contextlib.redirect_stdout(buf):
                    plain(elapsed_s)
                self.progress.say(buf.getvalue().rstrip("\n"))

            self.sup.print_progress = print_progress
            self._thread.start()
        return self

    def _follow(self) -> None:
        while not self._stop.wait(0.5):
            st = self.sup.statuses.get(self.key)  # one dict read: no lock needed
            if st is None:
                continue
            done, _, total = str(st.details.get("progress", "")).partition("/")
            if not (done.isdigit() and total.isdigit()):
                continue
            if self.bar is None:
                self.bar = self.progress.bar(int(total), self.key[1], unit="scan")
            self.bar.update(int(done) - self.bar.n)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        if self.bar is not None:
            # the replay's last status may predate its last scans: its summary has the count
            if replay_completed(Path(self.sup.run_dir)):
                self.bar.update(self.bar.total - self.bar.n)
            self.bar.close()
        self._logs.__exit__(*exc)
