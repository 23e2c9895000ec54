#!/usr/bin/python3
# Inverted tetrahedra of a model's tetra layers along a run's tissue series,
# and the skin's mean displacement:
#   scripts/tet_inversion.py model.h5 RUN_OUT_DIR [--every N]
# RUN_OUT_DIR holds the tissue_*.vtu files of `orthosim run ... --out DIR`
# (their point arrays are the model's nodes in order, plus any vessel points
# after them). A tetrahedron counts as inverted when its signed volume has
# the opposite sign to its rest volume. Central springs alone do not resist
# inversion (docs/runtime.md, Inverted layers). numpy, h5py.
import glob
import sys

import h5py
import numpy as np

from model_arrays import layers_by_order, read_frame, rest_and_masses


def main():
    if len(sys.argv) < 3:
        raise SystemExit('usage: tet_inversion.py model.h5 RUN_OUT_DIR [--every N]')
    model, run = sys.argv[1], sys.argv[2]
    every = int(sys.argv[sys.argv.index('--every') + 1]) if '--every' in sys.argv else 1
    with h5py.File(model, 'r') as f:
        rest, _ = rest_and_masses(f)
        tets = {n: f['layers'][n]['tets'][:] for n in layers_by_order(f)
                if 'tets' in f['layers'][n] and f['layers'][n]['tets'].shape[0] > 0}
        skin = f['layers/sets/skin'][:].astype(int) if 'skin' in f['layers/sets'] else None
    files = sorted(glob.glob(run + '/tissue_*.vtu'))
    if not files:
        raise SystemExit(run + ': no tissue_*.vtu files')

    def volumes(x, t):
        a, b, c, d = (x[t[:, k]] for k in range(4))
        return np.einsum('ij,ij->i', b - a, np.cross(c - a, d - a)) / 6

    rest_sign = {n: np.sign(volumes(rest, t)) for n, t in tets.items()}
    print('t (s) ' + ' '.join('%s inverted (of %d)' % (n, len(t)) for n, t in tets.items()) +
          (' skin mean |u| (mm)' if skin is not None else ''))
    for k, path in enumerate(files):
        if k % every and k != len(files) - 1:
            continue
        t, disp = read_frame(path)
        x = rest + disp[:len(rest)]
        line = '%.3f ' % t + ' '.join('%d' % int((volumes(x, tt) * rest_sign[n] <= 0).sum()) for n, tt in tets.items())
        if skin is not None:
            line += ' %.2f' % (1e3 * np.linalg.norm(disp[skin], axis=1).mean())
        print(line)


main()
