"""Models by name: a local folder, or a Hugging Face hub id, as transformers and diffusers do.

    SegMo.from_pretrained("runs/demo/model")           # a folder
    SegMo.from_pretrained("someone/segmo-humanml3d")   # a hub repository (cached)
    model.save_pretrained("out", push_to_hub=True, repo_id="me/segmo-test")

Downloads go through `huggingface_hub` and its cache (``HF_HOME`` / ``HF_HUB_CACHE``);
with ``HF_HUB_OFFLINE=1``, or when the hub's host name does not resolve
(`segmo.network`), only the cache is read, so a model fetched once loads on a machine
without a network. A name that is a folder is always the folder.

Every model directory records the segmo version that wrote it and its format number
(`FORMAT`); a directory of a newer format is refused with the version that wrote it,
instead of failing somewhere in the weights.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from segmo.errors import SegmoError
from segmo.network import hub_unreachable

__all__ = ["FORMAT", "check_format", "is_hub_id", "resolve", "push_folder", "portable_path"]

# Format of config.json / segmo.json: raise it when a reader of today would misread a
# directory written with the change (not for new optional fields).
FORMAT = 1
_HUB_ID = re.compile(r"^[A-Za-z0-9][\w.-]*/[\w.-]+$")


def segmo_version() -> str:
    from segmo import __version__

    return __version__


def check_format(payload: dict, path: str | os.PathLike) -> None:
    """Refuse a config whose format is newer than this segmo reads (or not a number)."""
    found = payload.get("format", FORMAT)  # directories written before formats were recorded
    if isinstance(found, bool) or not isinstance(found, int) or found < 1:
        raise SegmoError(f"{path}: 'format' must be a whole number >= 1, got {found!r}")
    if found > FORMAT:
        writer = payload.get("segmo_version", "a newer segmo")
        raise SegmoError(f"{path}: written by segmo {writer} in format {found}; this segmo "
                         f"({segmo_version()}) reads format {FORMAT} and older; upgrade segmo")


def is_hub_id(name: str | os.PathLike) -> bool:
    """True for a name shaped like a hub repository id ("owner/name") that is no path here."""
    text = str(name)
    return bool(_HUB_ID.match(text)) and not Path(text).exists()


def resolve(name: str | os.PathLike, revision: str | None = None) -> Path:
    """The local folder of `name`: `name` itself when it is a folder, else the snapshot of
    the hub repository `name` ("owner/model") in the Hugging Face cache (downloaded
    unless ``HF_HUB_OFFLINE`` is set). SegmoError when it is neither."""
    if not isinstance(name, (str, os.PathLike)) or not str(name).strip():
        raise SegmoError(f"expected a model folder or a hub id like 'owner/name', got {name!r:.80}")
    path = Path(name)
    try:
        if path.is_dir():
            return path
        exists = path.exists()
    except OSError as error:  # a name too long for the file system, say
        raise SegmoError(f"{str(name)[:80]}...: not a model folder ({error.strerror})") from None
    text = str(name)
    if exists:
        raise SegmoError(f"{text}: is a file, not a model folder")
    if not is_hub_id(text):
        raise FileNotFoundError(f"{text}: no such model folder (nor a hub id like 'owner/name')")
    from huggingface_hub import constants, snapshot_download
    from huggingface_hub.errors import (
        HfHubHTTPError,
        HFValidationError,
        LocalEntryNotFoundError,
        RepositoryNotFoundError,
        RevisionNotFoundError,
    )

    unreachable = None if constants.HF_HUB_OFFLINE else hub_unreachable()  # offline: cache only
    try:
        return Path(snapshot_download(text, revision=revision, library_name="segmo",
                                      library_version=segmo_version(),
                                      local_files_only=bool(unreachable)))
    except LocalEntryNotFoundError:
        raise SegmoError(f"{text}: no such model folder, and the hub repository is not in the "
                         f"Hugging Face cache ({unreachable or 'offline, or no network'}); "
                         "download it once with a network, or pass a folder") from None
    except (RepositoryNotFoundError, RevisionNotFoundError) as error:
        raise SegmoError(f"{text}: no such model folder, and no such hub repository"
                         f"{f' at revision {revision!r}' if revision else ''} "
                         f"({type(error).__name__})") from None
    except HFValidationError as error:  # shaped like owner/name, but e.g. "a/b..c"
        raise SegmoError(f"{text}: no such model folder, nor a valid hub id ({error})") from None
    except HfHubHTTPError as error:
        raise SegmoError(f"{text}: the hub answered {error}") from None


def check_repo_id(repo_id: object) -> None:
    """SegmoError unless `repo_id` looks like a hub repository id, 'owner/name': checked
    before a folder is written for upload, not after."""
    if not isinstance(repo_id, str) or not _HUB_ID.match(repo_id):
        raise SegmoError(f"push_to_hub: repo_id must look like 'owner/name', got {repo_id!r}")


def push_folder(directory: str | os.PathLike, repo_id: str, private: bool = False,
                commit_message: str = "Upload segmo model", token: str | None = None) -> str:
    """Upload a written model folder to the hub repository `repo_id` (created if needed);
    returns the commit URL."""
    check_repo_id(repo_id)
    from huggingface_hub import HfApi

    api = HfApi(token=token, library_name="segmo", library_version=segmo_version())
    api.create_repo(repo_id, private=private, exist_ok=True)
    commit = api.upload_folder(repo_id=repo_id, folder_path=str(directory),
                               commit_message=commit_message)
    return str(getattr(commit, "commit_url", commit))


def portable_path(path: str | os.PathLike) -> str:
    """A path as it may be recorded in a shared model: relative to the working directory
    when it lies below it, else only its last two parts (no home directories in a
    published model)."""
    path = Path(path)
    if not path.is_absolute():
        return path.as_posix()
    try:
        return path.resolve().relative_to(Path.cwd().resolve()).as_posix()
    except ValueError:
        return Path(*path.parts[-2:]).as_posix()
