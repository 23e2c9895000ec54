#!/usr/bin/python3
# Inverted tetrahedra of a model's tetra layers along a run's tissue series:
#   scripts/tet_inversion.py model.h5 RUN_OUT_DIR [--every N]
# RUN_OUT_DIR holds the tissue_*.vtu files of `orthosim run ... --out DIR`
# (their point arrays are the model's nodes in order, plus any vessel points
# after them). A tetrahedron counts as inverted when its signed volume has
# the opposite sign to its rest volume. Central springs alone do not resist
# inversion (docs/msm.md, Limitations). numpy, h5py.
import glob, re, sys

import h5py
import numpy as np


def read_vtu(path):
    b = open(path, 'rb').read()
    i = b.index(b'<AppendedData encoding="raw">')
    head = b[:i].decode()
    data = b[b.index(b'_', i) + 1:]
    t = float(re.search(r'Name="TimeValue"[^>]*>([^<]+)<', head).group(1))
    for m in re.finditer(r'<DataArray type="(\w+)"( Name="(\w+)")? NumberOfComponents="(\d+)" format="appended" '
                         r'offset="(\d+)"', head):
        if m.group(1) == 'Float64' and m.group(3) == 'displacement':
            off = int(m.group(5))
            n = int(np.frombuffer(data[off:off + 8], '<u8')[0])
            return t, np.frombuffer(data[off + 8:off + 8 + n], '<f8').reshape(-1, 3)
    raise SystemExit(path + ': no displacement array')


def main():
    if len(sys.argv) < 3:
        raise SystemExit(__doc__ or 'usage: tet_inversion.py model.h5 RUN_OUT_DIR [--every N]')
    model, run = sys.argv[1], sys.argv[2]
    every = int(sys.argv[sys.argv.index('--every') + 1]) if '--every' in sys.argv else 1
    with h5py.File(model, 'r') as f:
        layers = [n for n in f['layers'] if n != 'sets']
        n_nodes = max(int(f['layers'][n].attrs['node_offset']) + f['layers'][n]['nodes'].shape[0] for n in layers)
        rest = np.zeros((n_nodes, 3))
        for n in layers:
            o = int(f['layers'][n].attrs['node_offset'])
            rest[o:o + f['layers'][n]['nodes'].shape[0]] = f['layers'][n]['nodes'][:]
        tets = {n: f['layers'][n]['tets'][:] for n in layers
                if 'tets' in f['layers'][n] and f['layers'][n]['tets'].shape[0] > 0}
    files = sorted(glob.glob(run + '/tissue_*.vtu'))
    if not files:
        raise SystemExit(run + ': no tissue_*.vtu files')

    def volumes(x, t):
        a, b, c, d = (x[t[:, k]] for k in range(4))
        return np.einsum('ij,ij->i', b - a, np.cross(c - a, d - a)) / 6

    rest_sign = {n: np.sign(volumes(rest, t)) for n, t in tets.items()}
    print('t (s) ' + ' '.join('%s inverted (of %d)' % (n, len(t)) for n, t in tets.items()))
    for k, path in enumerate(files):
        if k % every and k != len(files) - 1:
            continue
        t, disp = read_vtu(path)
        x = rest + disp[:n_nodes]
        print('%.3f ' % t + ' '.join('%d' % int((volumes(x, tt) * rest_sign[n] <= 0).sum()) for n, tt in tets.items()))


main()
