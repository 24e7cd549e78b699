"""What a run of `smana up` says about itself at the end: the supervisor's warnings (a service that
never became ready, crashed, kept crashing, or exited with an error; a service another needs that
never ran, here or on another host) and its progress line. A warning makes `smana up` exit 1.
"""

from __future__ import annotations

import signal

from smana.common import service_table
from smana.deploy.processes import Managed

# A service that exits with this status refused its configuration (`run_command`'s user errors):
# restarting it cannot help, so the stack stops and `smana up` exits with it.
CONFIG_ERROR = 2


class Outcome:
    """The supervisor's account of its run. Mixed into `Supervisor`, whose `procs`, `config`,
    `fleet`, `run_dir`, `seen_ready`, `statuses` and `_lock` it reads."""

    def warnings(self) -> list[str]:
        """What the supervisor saw go wrong in this run (the report adds what its figures show)."""
        out = []
        for m in self.procs.values():
            log_file = (
                m.log_path.relative_to(self.run_dir)
                if m.log_path.is_relative_to(self.run_dir)
                else m.log_path
            )
            if not m.ever_ready:
                out.append(f"{m.name} never became ready (see {log_file})")
            if m.crash_looped:
                codes = ", ".join(str(c) for c in m.exit_codes[-5:])
                out.append(
                    f"{m.name} kept crashing: restarted {m.n_restarts} times, more than "
                    f"{m.policy.max_restarts} in {m.policy.restart_window_s:.0f} s (last "
                    f"exit statuses {codes}; see {log_file})"
                )
            else:
                out += self._crash_lines(m, log_file)
            if m.finished and m.exit_codes and m.exit_codes[-1] not in (0, -signal.SIGINT):
                out.append(
                    f"{m.name} exited with status {m.exit_codes[-1]} and was not "
                    f"restarted (restart = {m.policy.restart})"
                )
        # What the service that ends the run (the explorer) needs to do its job (the table's
        # `needs`), here or on another host of the deployment.
        finish_with = service_table.row(self.config.deploy.finish_with)
        for m in [m for m in self.procs.values() if finish_with and m.service == finish_with.name]:
            for need in finish_with.needs:
                row = service_table.row(need)  # None: a plug-in's need no row names
                where = m.robot
                if self.fleet is not None and row is not None and row.shared_only:
                    where = self.fleet  # the fleet's shared graph and coordinator
                elif self.fleet is None and row is not None and row.fleet_only:
                    continue
                if (where, need) in self.seen_ready:
                    continue
                why = "see above"
                if self._find(where, need) is None:
                    why = f"disabled in this run (deploy.{need}.enabled = false) and none ran"
                    why += " elsewhere"
                out.append(
                    f"the {need} the {finish_with.name} of robot {m.robot} needs never came up "
                    f"({why})"
                )
        return out

    @staticmethod
    def _crash_lines(m: Managed, log_file) -> list[str]:
        """One line per crash that was restarted (or kill by the health checks): a run that
        recovered still says it crashed."""
        out = []
        for c in m.crashes:
            if c["back_s"] is None:
                back = "not ready again before the run ended"
            else:
                how = "a hot spare took over" if c["spare"] else "restarted"
                back = f"{how}, ready {c['back_s']:.2f} s after it ended"
            what = (
                f"was killed by the supervisor ({c['killed_for']})"
                if c["killed_for"]
                else "crashed"
            )
            out.append(
                f"{m.name} {what} {c['at_s']:.0f} s into the run (exit status {c['code']}; "
                f"{back}; see {log_file})"
            )
        return out

    def print_progress(self, elapsed_s: float) -> None:
        with self._lock:
            statuses = dict(self.statuses)
        parts = []
        for name, m in self.procs.items():
            st = statuses.get((m.robot, m.service))
            mark = (
                "up" if m.alive else "starting" if m.starting else "done" if m.finished else "down"
            )
            extra = ""
            if st is not None and st.pid == (m.proc.pid if m.proc else -1):
                # a stream's first messages, refused while its clock settles, are no news
                bad = sum(n for k, n in st.rejected.items() if k != "settling")
                extra = f" in={st.msgs_in} out={st.msgs_out}" + (f" rejected={bad}" if bad else "")
                progress = st.details.get("progress")
                if progress:
                    extra += f" {progress}"
            parts.append(f"{name}:{mark}{extra}")
        print(f"[{elapsed_s:6.0f} s] " + " | ".join(parts), flush=True)


def last_line(m: Managed) -> str:
    """The last line a service wrote to its log (a refusal is one line: its reason)."""
    try:
        lines = m.log_path.read_text(errors="replace").strip().splitlines()
    except OSError:
        lines = []
    return lines[-1].strip() if lines else f"exit status {CONFIG_ERROR}, empty log"
