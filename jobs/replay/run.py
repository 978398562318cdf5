"""``dualsight replay``: the cases of any run, chosen by ``--case`` or an SQL predicate, each verified against its row
and recorded for rerun by its kind's replay (jobs/replay/cases.py for star and any other kind, jobs/replay/prox.py
for proximity cases, jobs/replay/star_track.py for star-tracking sequences: every frame on the ``frame`` time line).
"""

from __future__ import annotations

from pathlib import Path

from dualsight.errors import InputError
from dualsight.jobs.replay.cases import recording_path, replay_generic_case, replay_star_case, select_cases
from dualsight.jobs.replay.prox import replay_prox_case
from dualsight.jobs.replay.rendezvous import replay_rendezvous_case
from dualsight.jobs.replay.star_track import replay_track_case
from dualsight.viz.recording import open_recording
from dualsight.warehouse.lake import Lake

__all__ = ["replay_run"]


def replay_run(lake: Lake, run_id: str, *, case: int | None = None, where: str | None = None, limit: int = 20,
               output: Path | None = None) -> tuple[list[Path], list[int]]:
    """Replay the selected cases of any run into rerun recordings: one ``.rrd`` file holding every selected
    case on the ``frame`` time line (a trajectory plays as a film), or one file per case in a folder
    (``<run>-case<N>.rrd``).  Every case is verified against its row first.  Returns (the files written, the
    case ids recorded)."""
    manifest, cases = select_cases(lake, run_id, case=case, where=where, limit=limit)
    if not cases:
        raise InputError("the predicate selects no case of this run", source="--where")
    output = Path(output) if output is not None else Path(".")
    single_file = output.suffix == ".rrd"
    folder = output.parent if single_file else output
    if single_file and folder.exists():
        recording_path(output)            # a file as folder, no room to write, a device or pipe: one line, no work
    elif not single_file and output.exists() and not output.is_dir():
        raise InputError("exists and is not a folder; give a folder or a .rrd file", source=str(output))
    if not folder.is_dir():
        if single_file or not folder.parent.is_dir():
            raise InputError("folder does not exist (no folder is created but the one named)", source=str(folder))
        folder.mkdir()
    for c in [] if single_file else cases:            # each file writable, none a folder/device/pipe, before any work
        recording_path(folder / f"{run_id}-case{c}.rrd")
    rec = open_recording(output) if single_file else None
    out = []
    for i, c in enumerate(cases):
        path = output if single_file else folder / f"{run_id}-case{c}.rrd"
        kind = manifest["kind"]
        if kind == "star":
            replay_star_case(lake, run_id, c, path, rec=rec)
        elif kind in ("prox_sweep", "prox_trajectory"):
            replay_prox_case(lake, run_id, c, path, rec=rec)
        elif kind == "star_track":
            replay_track_case(lake, run_id, c, path, rec=rec,       # sequences one after the other in one file
                              frame_offset=i * int(manifest["spec"]["sequence"]["frames"]) if single_file else 0)
        elif kind == "rendezvous":
            replay_rendezvous_case(lake, run_id, c, path, rec=rec)
        else:
            replay_generic_case(lake, manifest, c, path, rec=rec)
        if path not in out:
            out.append(path)
    if rec is not None:
        rec.flush()
    return out, [int(c) for c in cases]
