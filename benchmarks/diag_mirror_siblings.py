"""Diagnostic (issue 27, item 5; RESULTS "The mirror check on the tuning half"): for every mirror suspect of flag_mirrored, the rigid mirror ratio against each
other shape (its raw input), to see whether a 'same-handed sibling' separates either-sign
populations (global) from a true left/right mix-up (mirrored twisted beans)."""
import sys
import numpy as np
from core.correspondence import checks, establish_correspondence
from core.correspondence.pair import mirror_fit_ratio
from core.correspondence.store import open_mesh
from core.datasets.shapes import known_homology_shapes
from core.datasets.families import population
from core.types import TriMesh

orig = checks.flag_mirrored
def wrapped(run, results):
    flagged = orig(run, results)
    ratios = {i: results[i][0].get("mirror_ratio") for i in run.usable if i in results and results[i][0] is not None}
    for i in sorted(ratios):
        if ratios[i] is None or ratios[i] >= checks.MIRROR_SUSPECT:
            continue
        xi = open_mesh(run.prepared[i]).vertices
        rij = []
        for j in sorted(run.corresponded):
            if j == i: continue
            rij.append(mirror_fit_ratio(open_mesh(run.prepared[j]).vertices, xi, run.params))
        print(f"  suspect {run.names[i]} ref-ratio {ratios[i]:.2f} flagged={i in flagged} r_ij={np.round(sorted(rij),2)}", flush=True)
    return flagged
checks.flag_mirrored = wrapped

def run(label, meshes):
    print(label, flush=True)
    r = establish_correspondence(meshes, "auto", n_jobs=1, refine=0, safeguard=False)
    print("  failures", list(r.failures), flush=True)

if __name__ == '__main__':
    for seed in (100, 101, 102):
        run(f"global {seed}", population("global", 6, seed).meshes)
    for seed in (2, 3, 4):
        pop = known_homology_shapes("twist", 6, seed=seed, n_points=(380, 420))
        meshes = list(pop.meshes); m = meshes[4]
        meshes[4] = TriMesh(m.vertices * np.array([-1.0, 1.0, 1.0]), m.faces[:, ::-1], "mirrored")
        run(f"twist {seed} mirrored 4", meshes)
        meshes = list(pop.meshes)
        for k in (1, 4):
            m = meshes[k]; meshes[k] = TriMesh(m.vertices * np.array([-1.0, 1.0, 1.0]), m.faces[:, ::-1], f"mirrored{k}")
        run(f"twist {seed} mirrored 1,4", meshes)
