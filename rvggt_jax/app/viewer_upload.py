"""The viewer's upload form (`rvggt view OUT --weights CKPT`), upstream demo_gradio's:
images (one by one, or a .zip of them) or a video uploaded in the page are reconstructed on
the server by `rvggt_jax.app.commands.reconstruct_folder` into a new folder of a working
folder, the stages shown in the page, and the result replaces the one shown
(`rvggt_jax.app.viewer.Viewer.show`)."""

from __future__ import annotations

import io
import os
import threading
import time
import zipfile
from pathlib import Path, PurePosixPath

from rvggt_jax.app.viewer_data import _code, _md, load_reconstruction

__all__ = ["DEFAULT_WORK_DIR", "MAX_UNPACKED_BYTES", "UploadError", "UploadForm", "unpack_upload"]

DEFAULT_WORK_DIR = "rvggt_uploads"
MAX_UNPACKED_BYTES = 4 << 30  # images a .zip upload may unpack to (a guard against zip bombs)


class UploadError(ValueError):
    """An upload the form cannot take (the message says why, on one line)."""


def unpack_upload(name: str, content: bytes) -> dict[str, bytes]:
    """The input files one upload adds, {file name: bytes}: an image or a video as it is
    (under its base name), a .zip as the images in it (base names; folders, hidden files
    and other files skipped). `UploadError` for anything else, a .zip without images,
    with two images of one name, or unpacking to more than `MAX_UNPACKED_BYTES`."""
    from rvggt_jax.io.images import IMAGE_EXTENSIONS
    from rvggt_jax.io.video import VIDEO_EXTENSIONS

    base = PurePosixPath(name.replace("\\", "/")).name
    suffix = PurePosixPath(base).suffix.lower()
    if not base or base.startswith("."):
        raise UploadError(f"cannot take a file named {name!r}")
    if suffix in IMAGE_EXTENSIONS or suffix in VIDEO_EXTENSIONS:
        return {base: content}
    if suffix != ".zip":
        raise UploadError(f"{base} is not an image ({', '.join(IMAGE_EXTENSIONS)}), a .zip of images or a video "
                          f"({', '.join(VIDEO_EXTENSIONS)})")
    files: dict[str, bytes] = {}
    try:
        with zipfile.ZipFile(io.BytesIO(content)) as z:
            members = [m for m in z.infolist() if not m.is_dir()]
            members = [m for m in members if PurePosixPath(m.filename).suffix.lower() in IMAGE_EXTENSIONS
                       and not any(part.startswith(".") or part == "__MACOSX"
                                   for part in PurePosixPath(m.filename).parts)]
            if sum(m.file_size for m in members) > MAX_UNPACKED_BYTES:
                raise UploadError(f"{base} unpacks to more than {MAX_UNPACKED_BYTES >> 30} GiB of images")
            for m in members:
                stem = PurePosixPath(m.filename).name
                if stem in files:
                    raise UploadError(f"{base} holds two images named {stem}")
                files[stem] = z.read(m)
    except (zipfile.BadZipFile, OSError, EOFError) as e:
        raise UploadError(f"cannot unpack {base}: {e}") from None
    if not files:
        raise UploadError(f"no images in {base} (images: {', '.join(IMAGE_EXTENSIONS)})")
    return files


class UploadForm:
    """The panel folder "reconstruct new images" (upstream demo_gradio's form): files
    uploaded in the page (`unpack_upload`: images one by one, .zip files of images, or
    one video) are kept in memory; "reconstruct" writes them to `work_dir`/upload_NNN/
    input (a new NNN) and runs `reconstruct_folder(input, weights, upload_NNN/
    reconstruction, options)` in a background thread (`options`: default, with
    predictions.npz so that the "points from" switch works), one run at a time. The
    progress bar and the `status` line below it follow the stages (saving the inputs,
    reconstructing with the elapsed time, loading the result, "done: ..." or
    "failed: <the CLIError's message>"); the result then replaces the shown one."""

    # viewer: a rvggt_jax.app.viewer.Viewer (not imported: that module imports this one)
    def __init__(self, viewer, weights: str | os.PathLike, work_dir: str | os.PathLike, options=None):
        import viser

        from rvggt_jax.app.options import ReconstructOptions

        self.viewer, self.weights, self.work_dir = viewer, weights, Path(work_dir)
        self.options = ReconstructOptions(save_raw=True) if options is None else options
        self.pending: dict[str, bytes] = {}  # file name -> content, in upload order
        self.busy = False
        self.last_out: Path | None = None  # the folder of the last finished run
        self.thread: threading.Thread | None = None  # the last run's, once started
        self._lock = threading.Lock()
        gui = viewer.server.gui
        with gui.add_folder("reconstruct new images", expand_by_default=True):
            gui.add_markdown(f"Add images one by one, a .zip of images or one video, then reconstruct them with "
                             f"{_code(weights)} into a new folder of {_code(self.work_dir)}.")
            self.upload_button = gui.add_upload_button(
                "add images / .zip / video", icon=viser.Icon.UPLOAD, mime_type="image/*,video/*,.zip,application/zip",
                hint="one file per upload; a .zip adds every image in it")
            self.pending_note = gui.add_markdown("no files yet")
            self.run_button = gui.add_button("reconstruct", icon=viser.Icon.PLAYER_PLAY, disabled=True)
            self.clear_button = gui.add_button("clear the files", icon=viser.Icon.TRASH, disabled=True)
            self.progress = gui.add_progress_bar(0.0, visible=False)
            self.status = gui.add_markdown("")
        self.upload_button.on_upload(lambda _: self.add(self.upload_button.value.name,
                                                        self.upload_button.value.content))
        self.run_button.on_click(lambda _: self.run())
        self.clear_button.on_click(lambda _: self.clear())

    # -- the files ------------------------------------------------------------------------

    def add(self, name: str, content: bytes) -> None:
        """Take one uploaded file (what the upload button calls); a file it cannot take
        is said in `status`."""
        with self._lock:
            if self.busy:
                self._say("failed", "a reconstruction is running: add files once it is done")
                return
            try:
                files = unpack_upload(name, content)
            except UploadError as e:
                self._say("failed", str(e))
                return
            replaced = [n for n in files if n in self.pending]
            self.pending.update(files)
            self._say("added", f"{len(files)} file{'s' * (len(files) != 1)} from {name}" +
                      (f" (replacing {', '.join(replaced)})" if replaced else ""))
            self._show_pending()

    def clear(self) -> None:
        with self._lock:
            if not self.busy:
                self.pending = {}
                self._show_pending()
                self._say("", "")
                self.progress.visible = False

    def _show_pending(self) -> None:
        names = list(self.pending)
        shown = ", ".join(names[:8]) + (f" and {len(names) - 8} more" if len(names) > 8 else "")
        self.pending_note.content = (f"{len(names)} file{'s' * (len(names) != 1)} to reconstruct: {_md(shown)}"
                                     if names else "no files yet")
        self.run_button.disabled = self.clear_button.disabled = self.busy or not names
        self.upload_button.disabled = self.busy  # the files of a run are fixed once it starts

    def _say(self, word: str, text: str) -> None:
        """`status`: **word**: text (both empty: nothing)."""
        self.status.content = f"**{word}**: {_md(text)}" if word else ""

    def _stage(self, value: float, word: str, text: str, animated: bool = False, color=None) -> None:
        self.progress.visible = True
        self.progress.value = value
        self.progress.animated = animated
        self.progress.color = color
        self._say(word, text)

    # -- the run --------------------------------------------------------------------------

    def run(self) -> threading.Thread | None:
        """Reconstruct the pending files in a background thread (returned; None when
        there is nothing to run, or a run is going on)."""
        from rvggt_jax.io.video import VIDEO_EXTENSIONS

        with self._lock:
            if self.busy or not self.pending:
                return None
            videos = [n for n in self.pending if PurePosixPath(n).suffix.lower() in VIDEO_EXTENSIONS]
            if videos and len(self.pending) > 1:
                self._say("failed", f"a video is reconstructed alone: clear the files and add only {videos[0]}")
                return None
            try:
                folder = self._new_folder()
                inputs = folder / "input"
                self._stage(5, "saving", f"{len(self.pending)} files to {inputs}")
                inputs.mkdir()
                for n, content in self.pending.items():
                    (inputs / n).write_bytes(content)
            except OSError as e:
                self._stage(100, "failed", f"cannot write the uploads under {self.work_dir}: {e.strerror or e}",
                            color="red")
                return None
            source = inputs / videos[0] if videos else inputs
            self.busy = True
            self._show_pending()
            thread = threading.Thread(target=self._work, args=(source, folder / "reconstruction"),
                                      name="rvggt-view-reconstruct", daemon=True)
            thread.start()
            self.thread = thread  # (once started: a thread not started yet is not alive either)
            return thread

    def _new_folder(self) -> Path:
        """A new `work_dir`/upload_NNN (made here: two viewers on one working folder
        never share one)."""
        self.work_dir.mkdir(parents=True, exist_ok=True)
        i = 1
        while True:
            folder = self.work_dir / f"upload_{i:03d}"
            try:
                folder.mkdir()
                return folder
            except FileExistsError:
                i += 1

    def _work(self, source: Path, out: Path) -> None:
        from rvggt_jax.app.commands import reconstruct_folder
        from rvggt_jax.app.messages import CLIError, one_line

        t0 = time.perf_counter()
        n = len(self.pending)
        what = f"{'a video' if source.is_file() else f'{n} image' + 's' * (n != 1)} with {self.weights}"
        done = False
        stop = threading.Event()

        def tick():  # the elapsed time, so that a long first compile is seen to be going on
            while not stop.wait(1.0):
                self._say("reconstructing", f"{what} ({time.perf_counter() - t0:.0f} s; the first run compiles "
                                            f"the model)")

        self._stage(15, "reconstructing", f"{what} (the first run compiles the model)", animated=True)
        ticker = threading.Thread(target=tick, daemon=True)
        ticker.start()
        try:
            try:
                reconstruct_folder(source, self.weights, out, self.options)
            finally:
                stop.set()
                ticker.join()
            self._stage(90, "loading", f"the result from {out}")
            rec = load_reconstruction(out)
            self.viewer.show(rec, out)
        except CLIError as e:
            self._stage(100, "failed", one_line(str(e), 1000), color="red")
        except Exception as e:  # noqa: BLE001 - said in the page, as `rvggt` says it on the terminal
            self._stage(100, "failed", f"{type(e).__name__}: {one_line(e, 1000)}", color="red")
            if os.environ.get("RVGGT_DEBUG"):
                raise
        else:
            done = True
            self.last_out = out
            self._stage(100, "done", f"{len(rec.names)} cameras, {len(rec.points)} points in "
                                     f"{time.perf_counter() - t0:.0f} s -> {out}", color="green")
        finally:
            with self._lock:
                if done:  # a failed run keeps its files for another try
                    self.pending = {}
                self.busy = False
                self._show_pending()
