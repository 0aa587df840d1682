"""``endoflow reconstruct`` over many videos: one Ray task per video, one output folder per video.

The inputs are video files and folders of them (:func:`video_files`). Each video is reconstructed into
``<out>/<its name without suffix>/`` by :func:`~endoflow.reconstruction.reconstruct.reconstruct`, so each folder is
staged and swapped in whole, as a single video's is. The tasks run on the cluster at ``ray.address`` (a local Ray
on loopback when it is null: :func:`endoflow.ray_runtime.connect_ray`), each reserving ``threads`` CPUs and, where
the device asks for one, a GPU. A video that fails is named with its error and the others go on; its folder is left
as it was. A folder that an earlier run made from the same video, model and settings (``resume_key`` in its
``reconstruction.json``) is kept, so a rerun does only the videos still missing or failed. Every node reads the
videos and the model and writes ``--out`` at the same paths: they must be on a filesystem every node shares.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import sys
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Iterator, Optional, Sequence, TextIO

from endoflow.config import ConfigError, RayConfig
from endoflow.data.video import IMAGE_SUFFIXES, VIDEO_SUFFIXES, natural_order
from endoflow.devices import use_cpu_threads
from endoflow.errors import DataFormatError
from endoflow.io import OutputFolderError, check_replaceable, file_sha256
from endoflow.progress import Progress, format_duration
from endoflow.ray_runtime import connect_ray, is_terminal, uncoloured_prefixes
from endoflow.reconstruction.frames import VideoFrames, intrinsics_for
from endoflow.reconstruction.reconstruct import (
    EARLIER_RECONSTRUCTION,
    RECONSTRUCTION_FORMAT,
    ReconstructOptions,
    VOXEL_DEFAULT,
    reconstruct,
)

# errors whose message names the file and what was wrong, shown as they are (any other error with its type)
EXPLAINED_ERRORS = (ConfigError, DataFormatError, FileNotFoundError, OutputFolderError)
# what --device may be for tasks on Ray: cuda:N names a GPU of this machine, which means nothing on another node
TASK_DEVICES = ("auto", "cpu", "cuda")


@dataclass(frozen=True)
class ManySettings:
    """What every video's task shares: the model file, ``intrinsics`` as ``--intrinsics`` gives them for every
    video (None: unknown, so learned or assumed as for one video, see
    :func:`~endoflow.reconstruction.reconstruct.input_intrinsics`), the options, and torch's CPU threads, which
    are also the CPUs a task reserves."""

    model: Path
    intrinsics: Optional[str]
    options: ReconstructOptions
    threads: int


@dataclass(frozen=True)
class VideoJob:
    """One video, the folder it is reconstructed into and its resume key (:func:`resume_key`)."""

    video: Path
    out: Path
    key: str


@dataclass
class ManyOutcome:
    """What became of the videos reconstructed into ``out``: reconstructed now (with the summary each task
    returned), kept from an earlier run, or failed (with the error)."""

    out: Path
    done: list[tuple[VideoJob, dict]] = field(default_factory=list)
    kept: list[VideoJob] = field(default_factory=list)
    failed: list[tuple[VideoJob, str]] = field(default_factory=list)

    @property
    def total(self) -> int:
        return len(self.done) + len(self.kept) + len(self.failed)


# ------------------------------------------------------------------------------------------------ inputs
def holds_videos(path: Path) -> bool:
    """Whether ``path`` is a folder with video files in it: one such input is many videos."""
    return path.is_dir() and bool(files_in(path, VIDEO_SUFFIXES))


def video_files(inputs: Sequence[Path]) -> list[Path]:
    """The videos of ``inputs``, each a video file or a folder whose video files (not its sub-folders) are taken
    in natural name order; a file given twice counts once.

    Raises:
        FileNotFoundError: naming an input that does not exist.
        DataFormatError: naming an input that is neither a video nor a folder of videos, or a folder that holds
            both videos and images (many videos, or the frames of one?).
    """
    videos: dict[Path, Path] = {}
    for path in inputs:
        for video in videos_of(path):
            videos.setdefault(video.resolve(), video)
    return list(videos.values())


def videos_of(path: Path) -> list[Path]:
    """The video ``path`` is, or the videos of the folder ``path``."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such video or folder of videos")
    if path.is_dir():
        return videos_in_folder(path)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise DataFormatError(path, f"is not a video file (expected {', '.join(VIDEO_SUFFIXES)}): with several "
                                    f"inputs each is a video or a folder of videos")
    return [path]


def videos_in_folder(folder: Path) -> list[Path]:
    videos, images = files_in(folder, VIDEO_SUFFIXES), files_in(folder, IMAGE_SUFFIXES)
    if videos and images:
        raise DataFormatError(folder, f"holds both videos ({len(videos)}, such as {videos[0].name}) and images "
                                      f"({len(images)}, such as {images[0].name}), so it is not clear whether it "
                                      f"is many videos or the frames of one: give the videos as paths, or pick the "
                                      f"frames with --pattern")
    if not videos:
        raise DataFormatError(folder, f"holds no video files ({', '.join(VIDEO_SUFFIXES)}); a folder of images is "
                                      f"the frames of one video: reconstruct it on its own")
    return videos


def files_in(folder: Path, suffixes: tuple[str, ...]) -> list[Path]:
    """The files of ``folder`` (not below it) ending in one of ``suffixes``, in natural name order; hidden files
    are left out (a macOS copy's ``._clip.mp4`` beside ``clip.mp4`` holds metadata, not video)."""
    return sorted((path for path in folder.iterdir()
                   if path.suffix.lower() in suffixes and not path.name.startswith(".") and path.is_file()),
                  key=natural_order)


# -------------------------------------------------------------------------------------------------- plan
def plan_jobs(videos: list[Path], out: Path, settings: ManySettings) -> list[VideoJob]:
    """A job per video into ``out/<stem>``, each folder checked before any work starts as a single run checks
    its ``--out`` (:func:`endoflow.io.check_replaceable`: new, empty or an earlier reconstruction, or ``force``;
    never holding the video or the model). Paths are made absolute: a task on another node does not work in the
    driver's folder.

    Raises:
        OutputFolderError: for an ``out`` that is a file, two videos of one name, or a folder that may not be
            replaced.
    """
    if out.exists() and not out.is_dir():
        raise OutputFolderError(f"{out}: is a file; with several videos --out is the folder that gets one "
                                f"folder per video")
    check_distinct_names(videos, out)
    model_sha256 = file_sha256(settings.model)
    jobs = []
    for video in videos:
        folder = out.absolute() / video.stem
        check_replaceable(folder, EARLIER_RECONSTRUCTION, settings.options.force, (video, settings.model),
                          "--force")
        jobs.append(VideoJob(video.absolute(), folder, resume_key(video, settings, model_sha256)))
    return jobs


def absolute_paths(settings: ManySettings) -> ManySettings:
    """``settings`` with the model and an intrinsics file as absolute paths, for tasks on other nodes."""
    spec = settings.intrinsics
    given_file = spec is not None and Path(spec).is_file()
    return replace(settings, model=settings.model.absolute(),
                   intrinsics=str(Path(spec).absolute()) if given_file else spec)


def check_distinct_names(videos: list[Path], out: Path) -> None:
    """Refuse videos whose output folders would be one, naming them. Names that differ in case only count as
    one: a filesystem that ignores case (macOS, Windows) gives them one folder."""
    by_name: dict[str, list[Path]] = {}
    for video in videos:
        by_name.setdefault(video.stem.casefold(), []).append(video)
    clashes = [" and ".join(map(str, paths)) for paths in by_name.values() if len(paths) > 1]
    if clashes:
        raise OutputFolderError(f"{out}: videos of one name would share an output folder ({'; '.join(clashes)}); "
                                f"rename them, or reconstruct them into separate --out folders")


def resume_key(video: Path, settings: ManySettings, model_sha256: str) -> str:
    """A hash of what a video's folder is made from: the reconstruction format, the video file (path, size and
    modification time: hashing hours of video would read all of it on every run), the model's bytes, the
    intrinsics given (a file by its path, size and time), the options but ``force`` (which changes no output),
    the default voxel's rule (where none is given) and the thread count (another count sums in another order)."""
    spec = settings.intrinsics
    record = {"format": RECONSTRUCTION_FORMAT, "voxel_default": VOXEL_DEFAULT, "video": file_state(video),
              "model": model_sha256,
              "intrinsics": file_state(Path(spec)) if spec is not None and Path(spec).is_file() else spec,
              "options": {**asdict(settings.options), "force": None}, "threads": settings.threads}
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()


def file_state(path: Path) -> list:
    """``[absolute path, size, mtime_ns]``: what tells a changed file from the one a folder was made from."""
    status = path.stat()
    return [str(path.resolve()), status.st_size, status.st_mtime_ns]


def holds_reconstruction(job: VideoJob) -> bool:
    """Whether ``job.out`` is a reconstruction with ``job``'s resume key (an earlier run's, or this run's task's);
    it is complete, as a reconstruction folder only ever appears whole."""
    try:
        summary = json.loads((job.out / "reconstruction.json").read_text())
    except (OSError, ValueError):  # missing, unreadable or not JSON
        return False
    return (isinstance(summary, dict) and summary.get("format") == RECONSTRUCTION_FORMAT
            and summary.get("resume_key") == job.key)


# --------------------------------------------------------------------------------------------------- run
def reconstruct_videos(videos: list[Path], out: Path, settings: ManySettings, cluster: RayConfig) -> ManyOutcome:
    """Reconstruct each of ``videos`` into ``out/<stem>/`` (module docstring); returns what became of each. Ray
    is started (or joined) only when a video needs reconstructing, and shut down again by this call.

    Raises:
        ConfigError, OutputFolderError: before any video's work starts, for a device a task cannot be given,
            folders that may not be replaced, or tasks no node of the cluster has room for.
    """
    if settings.options.device not in TASK_DEVICES:
        raise ConfigError(f"--device {settings.options.device}: each video's Ray task is given a GPU of its own "
                          f"where it needs one; use {', '.join(TASK_DEVICES)}")
    settings = absolute_paths(settings)
    jobs = plan_jobs(videos, out, settings)
    outcome = ManyOutcome(out, kept=[job for job in jobs if holds_reconstruction(job)])
    if outcome.kept:
        print(f"[reconstruct] {len(outcome.kept)} of {counted(len(jobs), 'video')} kept: reconstructed by an earlier "
              f"run from the same video, model and settings", file=sys.stderr)
    todo = [job for job in jobs if job not in outcome.kept]
    if todo:
        run_video_tasks(todo, settings, cluster, outcome)
    return outcome


def run_video_tasks(jobs: list[VideoJob], settings: ManySettings, cluster: RayConfig, outcome: ManyOutcome) -> None:
    """Run one Ray task per job, recording each result in ``outcome`` as it arrives."""
    import ray

    joined = connect_ray(cluster)
    try:
        gpus = task_gpus(settings.options.device)
        check_a_node_fits(settings.threads, gpus)
        shared = replace(settings, options=replace(settings.options, device="cuda" if gpus else "cpu"))
        task = ray.remote(num_cpus=settings.threads, num_gpus=gpus)(reconstruct_video)
        print(f"[reconstruct] {counted(len(jobs), 'video')} to reconstruct, a Ray task of "
              f"{counted(settings.threads, 'CPU')}{' and 1 GPU' if gpus else ''} each", file=sys.stderr, flush=True)
        # Ray prints the tasks' lines after a coloured "(reconstruct_video pid=...)": a file or a pipe gets no colours
        with contextlib.nullcontext() if is_terminal(sys.stderr) else uncoloured_prefixes():
            collect_results({task.remote(job, shared): job for job in jobs}, outcome)
    finally:
        if joined:
            ray.shutdown()


def task_gpus(device: str) -> int:
    """GPUs each task reserves: one for ``cuda``, and for ``auto`` where the cluster has GPUs. A task that
    reserves none computes on the CPU, even on a node with a GPU (another task may hold it)."""
    import ray

    if device == "cpu":
        return 0
    return 1 if device == "cuda" or ray.cluster_resources().get("GPU", 0) >= 1 else 0


def check_a_node_fits(cpus: int, gpus: int) -> None:
    """Raise :class:`ConfigError` when no live node of the cluster has room for one task: Ray would wait for one
    without a time limit."""
    import ray

    nodes = [node["Resources"] for node in ray.nodes() if node["Alive"]]
    if any(node.get("CPU", 0) >= cpus and node.get("GPU", 0) >= gpus for node in nodes):
        return
    largest = max(nodes, key=lambda node: (node.get("CPU", 0), node.get("GPU", 0)), default={})
    gpu = " and 1 GPU (--device)" if gpus else ""
    raise ConfigError(f"each video's Ray task reserves {counted(cpus, 'CPU')} (--threads; default: the model's "
                      f"threads){gpu}, and no node of the Ray cluster has them (largest: {largest.get('CPU', 0):g} "
                      f"CPUs, {largest.get('GPU', 0):g} GPUs); pass a lower --threads"
                      + (" or --device cpu" if gpus else ""))


def collect_results(pending: dict[Any, VideoJob], outcome: ManyOutcome) -> None:
    """Record each task's result in ``outcome`` as it finishes, with a progress line; on an interruption (Ctrl-C)
    the tasks still queued or running are stopped before it is raised."""
    progress = Progress(len(pending), "videos")
    try:
        while pending:
            job, summary, error = next_result(pending)
            error = error or arrival_problem(job)
            if error is None:
                outcome.done.append((job, summary))
                what = (f"{job.video.name}: {summary['frames']} frames in {format_duration(summary['seconds'])} "
                        f"-> {job.out}")
            else:
                outcome.failed.append((job, error))
                what = f"{job.video.name} failed: {error}"
            print(f"[reconstruct] {videos_progress(outcome, progress)} | {what}", file=sys.stderr, flush=True)
    except BaseException:
        stop_tasks(list(pending))
        raise


def next_result(pending: dict[Any, VideoJob]) -> tuple[VideoJob, Optional[dict], Optional[str]]:
    """The job of the next task to finish (removed from ``pending``), with its summary or its error."""
    import ray

    [ref], _ = ray.wait(list(pending), num_returns=1)
    job = pending.pop(ref)
    try:
        return job, ray.get(ref), None
    except ray.exceptions.RayTaskError as error:  # the task raised: its own error tells what was wrong
        return job, None, error_text(error.cause if isinstance(error.cause, Exception) else error)
    except ray.exceptions.RayError as error:  # its worker or node died, after Ray's retries
        return job, None, error_text(error)


def error_text(error: Exception) -> str:
    if isinstance(error, EXPLAINED_ERRORS):
        return str(error)
    lines = str(error).strip().splitlines()
    return f"{type(error).__name__}: {lines[0] if lines else ''}"


def arrival_problem(job: VideoJob) -> Optional[str]:
    """Why the folder a task wrote is not here, or None: a task on another node writes that node's disk unless
    ``--out`` is shared (an earlier run's folder here then stays, without this run's resume key)."""
    if holds_reconstruction(job):
        return None
    return (f"{job.out}: written by a Ray task on another node, not here: --out must be a folder every node of the "
            f"cluster shares, at the same path")


def videos_progress(outcome: ManyOutcome, progress: Progress) -> str:
    """``3/12 videos, ~4m10s left`` (at the pace of the videos reconstructed so far; failures take no time), or
    ``12/12 videos, done in 5m30s``."""
    finished, reconstructed = len(outcome.done) + len(outcome.failed), len(outcome.done)
    count = f"{finished}/{progress.total} videos"
    if progress.finished(finished):
        return f"{count}, done in {format_duration(progress.elapsed())}"
    if not reconstructed:
        return f"{count}, time left not known yet"
    return f"{count}, ~{format_duration(progress.elapsed() / reconstructed * (progress.total - finished))} left"


def stop_tasks(pending: list) -> None:
    """Cancel the tasks still queued or running and wait until each has ended: a cancelled task removes its
    staged folder as it stops (:func:`endoflow.io.staged_directory`), so none is still written when this
    returns."""
    import ray

    for ref in pending:
        ray.cancel(ref)
    if pending:
        print(f"[reconstruct] stopping {len(pending)} video tasks", file=sys.stderr, flush=True)
        ray.wait(pending, num_returns=len(pending))


# -------------------------------------------------------------------------------------------- in the task
def reconstruct_video(job: VideoJob, settings: ManySettings) -> dict:
    """A Ray task: one video into ``job.out``, its lines on stderr named after the video; returns its summary."""
    use_cpu_threads(settings.threads)
    with lines_named(job.video.name):
        check_readable_here(job.video, settings.model)
        frames = VideoFrames(job.video)
        K = intrinsics_for(settings.intrinsics, frames, settings.options.crop)
        return reconstruct(frames, K, settings.model, job.out, settings.options, job.key)


def check_readable_here(*files: Path) -> None:
    """Raise FileNotFoundError naming a file this node does not have, and why it needs it."""
    import ray

    for path in files:
        if not path.is_file():
            raise FileNotFoundError(f"{path}: not found on the Ray node {ray.util.get_node_ip_address()}: the "
                                    f"videos and the model must be on a filesystem every node shares, at the same "
                                    f"path")


@contextlib.contextmanager
def lines_named(name: str) -> Iterator[None]:
    """Within: every line written to stderr starts with ``name``. The driver shows a task's lines after the
    task's process id only, and the lines of videos reconstructed at once interleave."""
    named = NamedLines(name, sys.stderr)
    try:
        with contextlib.redirect_stderr(named):
            yield
    finally:
        named.finish()


class NamedLines(io.TextIOBase):
    """A text stream writing each whole line to ``stream`` after ``name: ``."""

    def __init__(self, name: str, stream: TextIO) -> None:
        super().__init__()
        self.name, self.stream, self.partial = name, stream, ""

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        *lines, self.partial = (self.partial + text).split("\n")
        for line in lines:
            self.stream.write(f"{self.name}: {line}\n")
        return len(text)

    def flush(self) -> None:
        self.stream.flush()

    def finish(self) -> None:
        """Write the last line, even without its newline."""
        if self.partial:
            self.write("\n")
        self.flush()


# ------------------------------------------------------------------------------------------------ summary
def format_outcome(outcome: ManyOutcome) -> str:
    """What a person reads at the end: counts, then each failed video with its error."""
    frames = sum(summary["frames"] for _, summary in outcome.done)
    lines = [f"{counted(outcome.total, 'video')} into {outcome.out}: {len(outcome.done)} reconstructed "
             f"({frames} frames), {len(outcome.kept)} kept from an earlier run, {len(outcome.failed)} failed"]
    lines += [f"  failed: {naming(job.video, error)}" for job, error in outcome.failed]
    return "\n".join(lines)


def naming(video: Path, error: str) -> str:
    """``error``, after the video's path unless it names the video already."""
    return error if str(video) in error else f"{video}: {error}"


def counted(count: int, noun: str) -> str:
    """``1 video``, ``2 videos``."""
    return f"{count} {noun}{'' if count == 1 else 's'}"
