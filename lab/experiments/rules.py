"""Rules fixed before the runs: one committed file per experiment, whose hash its data records.

An experiment's rules (its arms, seeds, metrics, margins, tests and the choices tuned on which
seeds) are written in `docs/experiments/rules/<name>.toml` before the runs that decide it. A run
of `smana experiment <name>` records that file's SHA-256 in the data it writes (`meta.rules`,
`stamp`), and `smana experiment report` refuses data whose rules file no longer has that hash
(`problems`): a rule changed after the runs, which the data cannot have been decided by. Data
made before an experiment had a rules file records none, and its section says so.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RULES_DIR = ROOT / "docs" / "experiments" / "rules"


def rules_file(name: str, rules_dir: Path | None = None) -> Path:
    return Path(rules_dir or RULES_DIR) / f"{name}.toml"


def digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def stamp(name: str, rules_dir: Path | None = None) -> dict | None:
    """{"file", "sha256"} of the experiment's rules file, None without one (an installed
    package carries no docs: its runs record none)."""
    path = rules_file(name, rules_dir)
    if not path.is_file():
        return None
    return {"file": f"docs/experiments/rules/{path.name}", "sha256": digest(path)}


def problems(all_data: dict[str, dict], rules_dir: Path | None = None) -> list[str]:
    """One line per data file whose recorded rules file is gone or has changed since its runs."""
    out = []
    for key, data in sorted(all_data.items()):
        recorded = (data.get("meta") or {}).get("rules")
        if not recorded:
            continue
        path = Path(rules_dir or RULES_DIR) / Path(recorded.get("file", "")).name
        if not path.is_file():
            out.append(f"{key}.json was decided under {recorded.get('file')}, which is gone")
        elif digest(path) != recorded.get("sha256"):
            out.append(
                f"{key}.json was decided under {recorded.get('file')} with SHA-256 "
                f"{str(recorded.get('sha256'))[:12]}..., which now hashes to "
                f"{digest(path)[:12]}...: its rules changed after the runs (restore them, or run "
                "again under the new ones)"
            )
    return out


def line(data: dict | None) -> str:
    """The sentence a section gives its rules: the file and hash its data was decided under."""
    recorded = ((data or {}).get("meta") or {}).get("rules")
    if not recorded:
        return "Its data records no rules file (made before the experiment had one)."
    return (
        f"Its data was decided under `{recorded['file']}` (SHA-256 "
        f"{recorded['sha256'][:12]}..., checked by `smana experiment report`)."
    )
