"""The inputs of a training-set run: read, groomed (or checked), and the reference remeshed.

The preparation step of Bernard et al., SPIE MI 2016 as the batch runs it
(:mod:`core.correspondence.batch`): every input file is read by a worker (each in a child
process: a reader crash costs that file only), every input groomed
(:mod:`core.correspondence.grooming`: largest piece, small holes, orientation, a common
vertex density) or, with grooming off, only checked (:func:`core.correspondence.pair.mesh_problem`),
each a per-shape job (:func:`core.runtime.parallel.run_jobs`: pool or Dask). Per usable
input the job also computes what reference selection needs (:mod:`core.correspondence.reference`),
where the mesh is. Then only the reference (candidates) is remeshed to the common count
(:func:`remesh_reference`, issue 27).
"""

from __future__ import annotations

import os
import warnings
from typing import TYPE_CHECKING, Any

import numpy as np

from core.correspondence.grooming import GroomingError, groom_mesh
from core.correspondence.pair import mesh_problem
from core.correspondence.reference import descriptor
from core.correspondence.store import InputFile, Scratch, open_mesh, read_input, write_scratch_mesh
from core.geometry import mesh as meshops
from core.runtime.parallel import JobError, preload_in_workers, run_jobs
from core.runtime.progress import sub_progress
from core.types import TriMesh

if TYPE_CHECKING:
    from core.correspondence.batch import CorrespondenceRun

preload_in_workers(__name__)  # reading and grooming jobs: workers start with this module imported

TARGET_KEEP_SHARE = 0.5  # inputs with at least this share of the common count keep their tessellation


def mesh_name(mesh: TriMesh | InputFile | str | os.PathLike, index: int) -> str:
    """How an input is named in errors and reports (a path: by itself)."""
    if isinstance(mesh, TriMesh):
        return mesh.name or f"mesh {index}"
    if isinstance(mesh, InputFile):
        return mesh.name or mesh.path
    return str(mesh)  # a path: named by it


def default_count(counts: list[int]) -> int:
    """The median of the input vertex counts (at least 20; 2000 when there are none)."""
    return max(int(np.median(counts)), 20) if counts else 2000


def shape_info(mesh: TriMesh) -> dict:
    """What reference selection needs of a usable (groomed) input: its pose- and
    scale-invariant descriptor and whether it is closed (computed where the mesh is)."""
    return {"descriptor": descriptor(mesh.vertices, mesh.faces),
            "closed": bool(meshops.is_closed(np.asarray(mesh.faces)))}


def read_job(item: tuple, raw_dir: str | None) -> tuple:
    """core.runtime.parallel job: read one input file -> (vertex count or None, problem or None, the
    reader's warnings for the client to show, the mesh to groom: in ``raw_dir`` if given
    (the grooming job then needs no second read of the file in a child), else itself)."""
    index, handle = item
    mesh, problem, notes = read_input(handle.path)
    if mesh is None:
        return None, problem, notes, None
    kept = mesh if raw_dir is None else write_scratch_mesh(mesh, raw_dir, index)
    return len(mesh.vertices), None, notes, kept


def groom_job(item: tuple, common: tuple) -> tuple:
    """core.runtime.parallel job: groom (or, with no options, only check) one input ->
    (groomed mesh or its scratch handle, report dict or None, None, info) or
    (None, None, problem, None). With a scratch directory the groomed mesh is written there
    and only its handle travels back."""
    index, handle = item
    options, scratch, name = common[0], common[1], common[2][index]
    mesh = open_mesh(handle)
    rep: dict | None
    if options is None:
        problem = mesh_problem(mesh)
        if problem:
            return None, None, problem, None
        groomed, rep = TriMesh(mesh.vertices, mesh.faces, name), None
    else:
        try:
            groomed, report = groom_mesh(mesh, options)
        except GroomingError as exc:
            return None, None, f"grooming: {exc}", None
        groomed.name = name
        rep = report.to_dict()
    info = shape_info(groomed)
    kept = groomed if scratch is None else write_scratch_mesh(groomed, scratch, index)
    return kept, rep, None, info


def read_inputs(run: CorrespondenceRun, meshes: list) -> tuple[dict[int, int], dict[str, str], list]:
    """Vertex count of every input, the inputs that cannot be read (name -> problem), and
    what to groom each from. Input files are read by the workers, each in a child process (a
    reader crash costs that file only); with a scratch folder the client never holds them."""
    from core.errors import DataFileWarning

    counts = {i: len(m.vertices) for i, m in enumerate(meshes) if isinstance(m, TriMesh)}
    sources = list(meshes)
    unread: dict[str, str] = {}
    files = [(i, (i, m)) for i, m in enumerate(meshes) if isinstance(m, InputFile)]
    if files:
        scratch = run.store
        done = run_jobs(read_job, files, common=None if scratch is None else str(scratch.raw),
                        n_jobs=run.n_jobs, label="reading", progress=sub_progress(run.progress, 0.0, 0.02))
        for i, _ in files:
            n, problem, notes, kept = done[i]
            for note in notes:
                warnings.warn(DataFileWarning(note), stacklevel=2)
            if problem is not None:
                unread[run.names[i]] = problem
            else:
                counts[i], sources[i] = n, kept
    return counts, unread, sources


def prepare_inputs(run: CorrespondenceRun, groom: bool | dict, vertices: int | None) -> None:
    """Groomed (or checked) inputs into ``run.prepared``, per-shape failures into
    ``run.failures`` (input order), grooming reports into ``run.grooming``, per usable input
    what reference selection needs into ``run.info`` (:func:`shape_info`, plus ``n_input``:
    its vertex count before grooming), and the inputs that could not be read into
    ``run.unread``. Grooming is a per-shape job too (:func:`core.runtime.parallel.run_jobs`).

    ``run.handles`` holds TriMesh objects or :class:`~core.correspondence.store.InputFile`
    handles (read by the workers). The groomed inputs come back as meshes, or with a
    scratch directory (``run.store``) as handles of the files the workers wrote there.
    """
    counts, unread, meshes = read_inputs(run, run.handles)
    run.unread = unread
    run.prepared = [None] * len(meshes)
    failures: dict[str, str] = dict(unread)
    if groom is False and run.store is None and all(isinstance(m, TriMesh) for m in meshes):
        for i, m in enumerate(meshes):  # in memory, nothing to groom: checked here
            problem = mesh_problem(m)
            if problem:
                failures[run.names[i]] = problem
            else:
                run.prepared[i] = m
                run.info[i] = dict(shape_info(m), n_input=counts[i])
        run.failures = failures
        return
    _groom_inputs(run, meshes, counts, failures, groom, vertices)
    run.failures = {n: failures[n] for n in run.names if n in failures}  # input order


def _groom_inputs(run: CorrespondenceRun, meshes: list, counts: dict[int, int],
                  failures: dict[str, str], groom: bool | dict, vertices: int | None) -> None:
    """The grooming (or checking) jobs of :func:`prepare_inputs` over the readable inputs."""
    readable = [i for i in range(len(meshes)) if i in counts]
    options = None
    if groom is not False:
        options = dict(groom) if isinstance(groom, dict) else {}
        options.setdefault("vertices", int(vertices) if vertices else
                           default_count([counts[i] for i in readable]))
        options.setdefault("keep_tessellation_above", TARGET_KEEP_SHARE)
    scratch = run.store
    common = (options, None if scratch is None else str(scratch.groomed), run.names)
    try:
        done = run_jobs(groom_job, [(i, (i, meshes[i])) for i in readable], common=common,
                        n_jobs=run.n_jobs, progress=sub_progress(run.progress, 0.02, 0.1),
                        label="grooming" if options is not None else "checking")
    except JobError as exc:  # an unexpected error of one input: raised as it is, as inline
        raise (exc.__cause__ or exc) from None
    if scratch is not None:
        scratch.drop_raw()  # the inputs as read: groomed now
    for i in readable:
        kept, rep, problem, shape = done[i]
        if problem is not None:
            failures[run.names[i]] = problem
            continue
        run.prepared[i] = kept
        run.info[i] = dict(shape, n_input=counts[i])
        if rep is not None:
            run.grooming[run.names[i]] = rep


def remesh_reference(run: CorrespondenceRun, candidates: list, groom: bool | dict,
                     vertices: int | None) -> None:
    """Only the reference (candidates) is remeshed to the common count; the targets keep
    their own tessellation unless coarse (grooming's ``keep_tessellation_above``).

    Why (issue 27; uneven beans, ``core.datasets.shapes.unevenly_decimated``, 8 shapes, seed
    1, true spread mean / p95 mm, reference-based): both remeshed 2.33 / 3.30, the targets
    alone remeshed 2.34 / 3.43, the reference alone 1.93 / 3.03, neither 1.98 / 3.36; with
    one refinement pass 0.77 / 1.17 both, 0.64 / 1.05 neither, 0.47 / 0.68 the reference
    alone. The remesh is accurate (0.007-0.014 mm from the input surface), so what the
    targets lose is their own vertex density: a quadric decimation's follows the curvature,
    the same on homologous parts of every shape, and CPD matches densities; an even remesh
    replaces it by one even in area, which the shapes' bumps and scalings skew. The
    reference is remeshed: its vertices are the model's, evenly spread, and its resolution
    then does not depend on which subject it is.
    """
    options: dict[str, Any] = dict(groom) if isinstance(groom, dict) else {}
    if groom is False or not options.get("remesh", True) or not run.info:
        return
    if options.get("keep_tessellation_above", TARGET_KEEP_SHARE) is None:
        return  # every input was remeshed already
    from core.correspondence.grooming import needs_remesh, remesh

    count = int(vertices) if vertices else default_count([d["n_input"] for d in run.info.values()])
    for c in candidates:
        if c is None:
            continue
        mesh = open_mesh(run.prepared[c])
        if not needs_remesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), count):
            continue
        v, f = remesh(np.asarray(mesh.vertices, float), np.asarray(mesh.faces), count)
        out = TriMesh(v, f, mesh.name)
        store: Scratch | None = run.store
        run.prepared[c] = out if store is None else write_scratch_mesh(out, store.groomed, c)
        rep = run.grooming.setdefault(run.names[c], {})
        rep.update(remeshed=True, output_vertices=int(len(v)))
