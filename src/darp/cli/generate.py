"""``darp twin generate -n N --seed S -o DIR``: N randomised twin surveys from one seed (darp.batch.generate)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from darp.cli._batch import ExecutorOption, batch_progress
from darp.cli._options import Profile, ProfileOption, Resolution, out_option, parse_resolution
from darp.cli.twin import twin_app


@twin_app.command("generate")
def generate_command(
    count: Annotated[int, typer.Option("--surveys", "-n", min=1, help="Number of surveys.",
                                       show_default=False)],
    out: Annotated[Path, out_option("Folder for the surveys (<out>/<NNNNNN_object>/) and generate.json.")],
    seed: Annotated[int, typer.Option("--seed", min=0, help="Seed of every draw of the batch.")] = 0,
    objects: Annotated[list[str] | None, typer.Option(
        "--object", help="Object to draw from: a twin object name or a mesh file; repeat (default: every paper "
        "object).", show_default=False)] = None,
    profile: ProfileOption = Profile.realistic,
    fps: Annotated[int, typer.Option("--fps", min=1, help="Camera frame rate.")] = 6,
    resolution: Annotated[Resolution | None, typer.Option(
        "--resolution", parser=parse_resolution, metavar="WIDTHxHEIGHT", help="Image size (default 424x240).",
        show_default=False)] = None,
    views: Annotated[int, typer.Option("--views", min=1, max=360, help="Orbit views per arm.")] = 3,
    executor: ExecutorOption = None,
) -> None:
    """Record N twin surveys with random objects, placements, yaws, materials and error draws (one task each)."""
    from darp.batch.executor import Executor
    from darp.batch.generate import generate_batch
    from darp.twin.objects.model import OBJECT_NAMES

    size = {} if resolution is None else {"width": resolution.width, "height": resolution.height}
    bar, progress = batch_progress(f"twin surveys on {executor or 'local'}", count)
    with bar:
        results = generate_batch(count, seed, list(objects or OBJECT_NAMES), out, executor or Executor(),
                                 progress=progress, profile=profile.value, fps=fps, views=views, **size)
    skipped = sum(bool(r.get("skipped")) for r in results)
    typer.echo(f"wrote {out} ({len(results) - skipped} surveys recorded, {skipped} already there)")
