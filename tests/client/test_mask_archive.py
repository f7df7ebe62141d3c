"""The masks' names the client expects before an upload are the server's (``client.mask_archive``)."""

from __future__ import annotations

from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from client.mask_archive import MASK_SUFFIX, mask_names, masks_already_there
from service.api.masks import MASK_SUFFIX as SERVER_SUFFIX
from service.core.names import MAX_NAME, unique_stems

NAMES = ["ax.nii.gz", "AX.nii", "x y.mha", "..hidden.nii.gz", "stacks[3].nrrd", "a.b.nii.gz", "é.nii", "", ".nii",
         "x" * 300 + ".nii.gz", "x" * 300 + ".nii", "scan.dcm", "scan.gz", "t2.NII.GZ"]


def server_names(names: list[str]) -> list[str]:
    return [s + SERVER_SUFFIX for s in unique_stems(names, MAX_NAME - len(SERVER_SUFFIX))]


def test_the_client_names_the_masks_as_the_server_does(tmp_path: Path) -> None:
    """Both rules, on names that each part of the rule changes (case, unsafe characters, lengths, extensions)."""
    assert MASK_SUFFIX == SERVER_SUFFIX
    named = [n or "_" for n in NAMES]                   # a file needs a name; the folder's own case below
    paths = [tmp_path / f"d{i}" / n for i, n in enumerate(named)]
    assert mask_names(paths) == server_names(named)
    folder = tmp_path / "series 1"                        # a DICOM folder goes as <folder>.zip
    folder.mkdir()
    assert mask_names([folder]) == server_names(["series 1.zip"]) == ["series_1_mask.nii.gz"]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.text(st.characters(codec="utf-8", exclude_characters="/\x00"), min_size=1, max_size=40)
                .filter(lambda n: n not in (".", "..")), min_size=1, max_size=5))
def test_the_rules_agree_on_any_names(names: list[str]) -> None:
    assert mask_names([Path("/nowhere") / n for n in names]) == server_names(names)


def test_a_made_unique_name_already_in_the_folder_is_found_before_the_upload(tmp_path: Path) -> None:
    (tmp_path / "ax-1_mask.nii.gz").write_bytes(b"")
    assert masks_already_there([Path("one/ax.nii.gz"), Path("two/ax.nii")], tmp_path) == ["ax-1_mask.nii.gz"]
    assert masks_already_there([Path("one/ax.nii.gz")], tmp_path) == []
