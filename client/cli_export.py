"""``svrnet export``: an answer's slice poses as NeSVoR or NiftyMIC read them (:mod:`client.peer_exports`),
so that those tools start from the poses instead of registering the slices themselves."""

from __future__ import annotations

import json
import shlex
from pathlib import Path
from typing import Annotated, Optional

import typer

from client.cli_support import MaskOpt, check_masks, once_or_per_stack, user_path
from client.exits import EXIT_BAD_INPUT, EXIT_NOTHING_USABLE, errors, fail, stderr, stdout

NEXT_STEP = {
    "nesvor": "nesvor reconstruct --input-slices {out} --output-volume recon.nii.gz",
    "niftymic": "niftymic_reconstruct_volume_from_slices --filenames {stacks}{masks}{thickness} --dir-input-mc {out} "
                "--reconstruction-space ATLAS_VOLUME.nii.gz --output recon.nii.gz",
}
"""What to run next, per tool (the docs give each in full: docs/reconstruction.md)."""
REGEX_CHARACTERS = frozenset("^$*+?{}[]\\|()")
"""Characters that change what NiftyMIC's pattern ``NAME_slice([0-9]+)[.]tfm`` matches."""


def export(
    answer: Annotated[Path, typer.Argument(exists=True, dir_okay=False, readable=True,
                                           help="JSON answer of `svrnet predict --out` or `reconstruct --poses-out`")],
    stacks: Annotated[list[Path], typer.Argument(
        exists=True, readable=True, metavar="STACK",
        help=".nii or .nii.gz: the files the answer was made from (NeSVoR and NiftyMIC read NIfTI; a scan "
             "sent as DICOM, NRRD or MHA: convert it, e.g. with dcm2niix, and predict from the NIfTI files)")],
    to: Annotated[str, typer.Option("--to", help="the tool to start: nesvor or niftymic")],
    out_dir: Annotated[Path, typer.Option("--out-dir", file_okay=False, callback=user_path,
                                          help="folder to write into (created; new or empty)")],
    mask: MaskOpt = None,
    all_slices: Annotated[bool, typer.Option(
        "--all-slices",
        help="also the slices not accepted (default: accepted ones only; never those without brain)")] = False,
    thickness: Annotated[Optional[list[float]], typer.Option(
        "--thickness", help="slice thickness in mm, once for every stack or once per stack (default: the slice "
        "spacing): NeSVoR's slice profile; NiftyMIC's --slice-thicknesses in the command printed")] = None,
    overwrite: Annotated[bool, typer.Option(
        "--overwrite", help="replace an earlier export in --out-dir (without it, a folder that holds anything "
                            "stops the command: each tool reads every slice file of its folder)")] = False,
) -> None:
    """Write the slice poses of an answer for NeSVoR (--input-slices) or NiftyMIC (--dir-input-mc): the
    stacks given are the NIfTI files the answer was made from, in its order."""
    check_masks(stacks, mask)
    once_or_per_stack(thickness, stacks, "--thickness")
    with errors():
        from client.peer_exports import FORMATS, export as write           # numpy, nibabel: only where needed
        if to not in FORMATS:
            raise typer.BadParameter(f"one of {', '.join(FORMATS)}", param_hint="--to")
        try:
            body = json.loads(answer.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            fail(f"{answer.name} is not a JSON answer ({e})", EXIT_BAD_INPUT)
        done = write(body, stacks, mask, out_dir, to, all_slices, thickness, overwrite)
    console = stdout()
    console.print(f"wrote {done.count} slices for {to} into {out_dir}", soft_wrap=True)
    if not done.count:
        stderr().print("no slice the answer trusts (none accepted, or none the job placed within its limit): "
                       "--all-slices writes every slice with brain, their expected errors in slices.tsv; or "
                       "start the tool from its own registration", style="yellow", markup=False)
        raise typer.Exit(EXIT_NOTHING_USABLE)
    if to == "nesvor" and not mask:
        stderr().print("no --mask: NeSVoR takes every pixel of each slice (the whole uterus of a stack as it leaves "
                       "the scanner); `svrnet masks` makes the masks", style="yellow", markup=False)
    if to == "niftymic":
        if done.stacks != list(stacks):
            stderr().print(f"NiftyMIC cuts slices along a file's third axis, reads NIfTI-1 files compressed as their "
                           f"names say and places them by their qform: the stacks stored otherwise were written again "
                           f"into {out_dir / 'stacks'}, their "
                           f"masks into {out_dir / 'masks'} (the same images); give NiftyMIC those", style="yellow",
                           markup=False)
        odd = [s.name for s in stacks if set(s.name) & REGEX_CHARACTERS]
        if odd:
            stderr().print(f"NiftyMIC finds a stack's .tfm files by a regular expression of its name: rename "
                           f"{', '.join(odd)} (no {''.join(sorted(REGEX_CHARACTERS))})", style="yellow", markup=False)
    quoted = lambda paths: " ".join(shlex.quote(str(p)) for p in paths)  # noqa: E731 - pasted into a shell
    masks = "" if not done.masks else " --filenames-masks " + quoted(done.masks)
    per_stack = [] if not thickness else thickness * len(stacks) if len(thickness) == 1 else thickness
    thick = "" if not per_stack else " --slice-thicknesses " + " ".join(f"{t:g}" for t in per_stack)
    console.print("next: " + NEXT_STEP[to].format(out=shlex.quote(str(out_dir)), stacks=quoted(done.stacks),
                                                  masks=masks, thickness=thick), soft_wrap=True, markup=False)
    if to == "niftymic":
        console.print("ATLAS_VOLUME.nii.gz: an atlas volume of the fetus's age in the atlas space the poses are in "
                      "(docs/pose-convention.md, \"Spaces\"): the reconstruction's grid and place", soft_wrap=True,
                      markup=False)
