"""The friction map of recorded runs and points tables, as `friction-map` makes it: every input
read (a points table, or a run checked against its cylinder file and cut into
constant-velocity points and breakaways), the map built with the rules for what it cannot be
made from, and its JSON document (docs/formats.md, "friction-map")."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from ..files import MAX_ROWS, cylinder_for_runs, read_run
from ..identify import preflight
from .map import FrictionMap, build_map
from .points import Breakaway, MapPoint, points_from_run
from .specs import FrictionMapError, SegmentOptions
from .tables import is_points_table, read_points

__all__ = ["MapInputs", "gather_map_inputs", "map_of_inputs"]


@dataclass
class MapInputs:
    """What the inputs give the map; `cyl` is the recorded runs' cylinder (None: tables only)."""

    paths: tuple[str, ...]
    segments: SegmentOptions
    cyl: object = None
    points: list[MapPoint] = field(default_factory=list)
    breakaways: list[Breakaway] = field(default_factory=list)
    runs: list[dict] = field(default_factory=list)  # per recorded run, as the JSON gives it
    stuck_time: float | None = None
    stuck_speeds: list[float] = field(default_factory=list)

    @property
    def names(self) -> str:
        return ", ".join(self.paths)

    def document(self, fmap: FrictionMap) -> dict:
        """friction-map's JSON: the map, its inputs and, for recorded runs, what each gave."""
        out = fmap.to_json()
        out["inputs"] = list(self.paths)
        if self.cyl is not None:
            s = self.segments
            out["config"] = str(self.cyl.source) if self.cyl.source else None
            out["runs"] = self.runs
            out["segment_options"] = {"min_duration": s.min_duration, "min_speed": s.min_speed, "spread": s.spread,
                                      "stuck_speed": max(self.stuck_speeds), "stuck_duration": s.stuck_duration}
        return out


def gather_map_inputs(paths: Sequence[str | Path], config: str | None, segments: SegmentOptions,
                      load: float | None = None, max_rows: int = MAX_ROWS,
                      say: Callable[[str], None] = lambda msg: None,
                      note: Callable[[str], None] = lambda msg: None) -> MapInputs:
    """Read every input in order: a points table's rows, or a recorded run's points and
    breakaways (its cylinder: `config`, else the one the first run names, else the built-in;
    identify's preflight refuses a run that cannot belong to it, its notes go to `note`)."""
    got = MapInputs(tuple(str(p) for p in paths), segments)
    for path in paths:
        if is_points_table(path):
            pts = read_points(path)
            got.points.extend(pts)
            nb = sum(p.breakaway for p in pts)
            say(f"{path}: points table, {len(pts) - nb} sliding points" + (f", {nb} breakaway rows" if nb else ""))
            continue
        run = read_run(path, max_rows)
        which = None
        if got.cyl is None:
            got.cyl, which = cylinder_for_runs(config, [run])
        for msg in preflight(got.cyl, [run]).notes:
            note(f"note: {msg}.")
        if which:  # once the run is accepted: a refusal stays the only line
            say(which)
        rp = points_from_run(got.cyl, run, segments, load=load)
        got.points.extend(rp.points)
        got.breakaways.extend(rp.breakaways)
        got.stuck_time = (got.stuck_time or 0.0) + rp.stuck_time
        got.stuck_speeds.append(rp.stuck_speed)
        got.runs.append({"source": str(path), "duration_s": rp.duration, "points": len(rp.points),
                         "breakaways": len(rp.breakaways), "stuck_time_s": rp.stuck_time,
                         "moving_time_s": rp.moving_time})
        say(f"{path}: run of {rp.duration:.1f} s, {len(rp.points)} constant-velocity points "
            f"({sum(p.v > 0 for p in rp.points)} extending, {sum(p.v < 0 for p in rp.points)} retracting), "
            f"{len(rp.breakaways)} breakaways")
    return got


def map_of_inputs(got: MapInputs, models: Sequence[str] | None = None, strict: bool = False,
                  progress: Callable[[str], None] | None = None) -> FrictionMap:
    """The map of what the inputs gave; FrictionMapError (one sentence naming the inputs) where
    they hold no sliding point, or no model could be fitted in any direction."""
    names, segments = got.names, got.segments
    if got.points and all(p.breakaway for p in got.points):
        raise FrictionMapError(f"{names}: only breakaway rows, no sliding points; give the map a sweep's points "
                               f"table or a recorded run beside the breakaway table.")
    if not got.points:
        raise FrictionMapError(f"{names}: no constant-velocity stretch found (at least {segments.min_duration:g} s "
                               f"above {segments.min_speed:g} m/s within {segments.spread:.0%} velocity spread); "
                               f"record moves at constant speed or relax --min-duration / --spread.")
    try:
        fmap = build_map(got.points, models, got.breakaways,
                         stuck_speed=max(got.stuck_speeds) if got.stuck_speeds else None, stuck_time=got.stuck_time,
                         min_speed=segments.min_speed if got.runs else None, strict=strict, progress=progress)
    except FrictionMapError as e:
        raise FrictionMapError(f"{names}: {e}") from None
    if not any(d.fits for d in fmap.directions.values()):
        # one reason per direction (they differ only in the model's name)
        reasons = "; ".join(next(iter(d.skipped.values())).rstrip(".") for d in fmap.directions.values() if d.skipped)
        raise FrictionMapError(f"{names}: no model could be fitted ({reasons}).")
    return fmap
