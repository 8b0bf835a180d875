"""Probe: flow_shading only at the points the decoupling test switched (not in omniflow).

Runs estimate() on frame pairs 0-2 of a dataset with the defaults and with
``flow_shading=SIGMA`` (the matches are the same: the matcher reads the frames
as given), takes the flattened run's flow where the default run decoupled a
point (``coupled`` 0, eq. (14) rejected) and the default's elsewhere
("mixed"), and prints cam1's EPE of the three and each object's mean flow
against the truth. Run::

    python benchmarks/shading_where_decoupled.py /work/data/independent_movers 8
"""

from __future__ import annotations

import sys
from collections import defaultdict

import numpy as np


def main(directory: str, sigma: float) -> None:
    from omniflow.config import OmniFlowConfig
    from omniflow.io.dataset import open_dataset
    from omniflow.pipeline import estimate
    from validation.inputs import Inputs, camera_model
    from validation.sampling import sample_truth

    ds = open_dataset(directory)
    camera = camera_model(ds.meta)
    inputs = Inputs(ds, camera, auto_exposure=camera is not None and "camera" not in ds.meta)
    epe: dict[str, list] = defaultdict(list)
    per_object: dict[tuple, list] = defaultdict(list)
    for t in (0, 1, 2):
        g1 = [inputs.grey(k, "cam1") for k in (t, t + 1)]
        g2 = [inputs.grey(k, "cam2") for k in (t, t + 1)]
        plain = estimate(g1, g2, ds.rig, OmniFlowConfig()).columns
        shaded = estimate(g1, g2, ds.rig, OmniFlowConfig(flow_shading=sigma)).columns
        assert np.array_equal(plain["x"], shaded["x"]), "the matches differ"
        dec = plain["coupled"] == 0
        mixed = {k: np.where(dec, shaded[k], plain[k]) for k in ("dh1_dt", "dtheta_dt")}
        truth = sample_truth(ds.read_frame(t, "cam1"), plain["x"], plain["y"])
        ok = truth["bilinear_ok"] & (truth["gt.valid"] > 0.5)
        obj = np.rint(truth["gt.object"]).astype(int)
        true_dh, true_tan = truth["gt.flow.dh"], truth["gt.flow.hdtheta"]
        for name, c in (("plain", plain), ("mixed", mixed), ("shaded", shaded)):
            tan = plain["h1"] * c["dtheta_dt"]
            epe[name].append(np.hypot(c["dh1_dt"] - true_dh, tan - true_tan)[ok])
            for i in np.unique(obj[ok]):
                m = ok & (obj == i)
                row = (c["dh1_dt"][m], true_dh[m], tan[m], true_tan[m], dec[m])
                per_object[(ds.objects.get(int(i), str(i)), name)].append(row)
        print(f"pair {t}: {dec.sum()} of {dec.size} points decoupled")
    for name, parts in epe.items():
        e = np.concatenate(parts)
        print(f"{name:7s} cam1 EPE mean / median {e.mean():.4f} / {np.median(e):.4f} px")
    print("object     run     points decoupled  dh est / true   h dtheta est / true  (px/frame)")
    for (obj_name, name), rows in sorted(per_object.items()):
        est, tru, tan, ttan, dec = (np.concatenate(col) for col in zip(*rows, strict=True))
        print(f"{obj_name:10s} {name:7s} {est.size:6d} {dec.sum():9d}  {est.mean():+.3f} / "
              f"{tru.mean():+.3f}   {tan.mean():+.3f} / {ttan.mean():+.3f}")  # fmt: skip


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]) if len(sys.argv) > 2 else 8.0)
