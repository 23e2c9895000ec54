"""Shared by scripts/msm_modes.py, static_sag.py and tet_inversion.py: a built
model's layers as global arrays, and a run's tissue frames (numpy, h5py)."""
import re

import numpy as np


def layers_by_order(f):
    """The names under /layers (the node sets aside), outer to inner."""
    return sorted([n for n in f['layers'] if n != 'sets'], key=lambda n: int(f['layers'][n].attrs['order']))


def rest_and_masses(f):
    """Rest positions (n x 3, m) and lumped masses (n, kg) by global node id."""
    layers = f['layers']
    names = layers_by_order(f)
    n = max(int(layers[k].attrs['node_offset']) + layers[k]['nodes'].shape[0] for k in names)
    rest, mass = np.zeros((n, 3)), np.zeros(n)
    for k in names:
        o, c = int(layers[k].attrs['node_offset']), layers[k]['nodes'].shape[0]
        rest[o:o + c] = layers[k]['nodes'][:]
        mass[o:o + c] += layers[k]['masses'][:]
    return rest, mass


def springs(f):
    """Every layer's biphasic springs, concatenated: ends, k1, k2, rest and turning lengths."""
    parts = [f['layers'][k] for k in layers_by_order(f)
             if 'springs' in f['layers'][k] and f['layers'][k]['springs'].shape[0] > 0]
    return tuple(np.concatenate([p[key][:] for p in parts])
                 for key in ('springs', 'k1', 'k2', 'rest_length', 'turning_length'))


def read_frame(path):
    """(time s, displacement n x 3 m) of one tissue_*.vtu frame of `orthosim run`."""
    b = open(path, 'rb').read()
    i = b.index(b'<AppendedData encoding="raw">')
    head = b[:i].decode()
    data = b[b.index(b'_', i) + 1:]
    t = float(re.search(r'Name="TimeValue"[^>]*>([^<]+)<', head).group(1))
    for m in re.finditer(r'<DataArray type="(\w+)"( Name="(\w+)")? NumberOfComponents="(\d+)" format="appended" '
                         r'offset="(\d+)"', head):
        if m.group(1) == 'Float64' and m.group(3) == 'displacement':
            off = int(m.group(5))
            size = int(np.frombuffer(data[off:off + 8], '<u8')[0])
            return t, np.frombuffer(data[off + 8:off + 8 + size], '<f8').reshape(-1, 3)
    raise SystemExit(path + ': no displacement array')
