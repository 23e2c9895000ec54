#!/usr/bin/python3
# The lowest vibration modes of a built model at rest (linear stiffness of the
# springs' first phase, lumped masses, the fixed set removed), and each
# mode's share of kinetic energy per layer: scripts/msm_modes.py model.h5
# (numpy, scipy, h5py; docs/msm.md, Limitations).
import sys
import time

import h5py
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from model_arrays import layers_by_order, rest_and_masses, springs

f = h5py.File(sys.argv[1], 'r')
L = f['layers']
layers = layers_by_order(f)
X, m = rest_and_masses(f)
N = len(m)
owner = np.empty(N, dtype=object)
for n in layers:
    o = L[n].attrs['node_offset']; k = L[n]['nodes'].shape[0]
    owner[o:o+k] = n
rows=[]; cols=[]; vals=[]
s, k1 = springs(f)[:2]
d = X[s[:,1]] - X[s[:,0]]; d /= np.linalg.norm(d, axis=1)[:,None]
for a in range(3):
    for b in range(3):
        kab = k1 * d[:,a] * d[:,b]
        for (i, j, sg) in ((0,0,1),(1,1,1),(0,1,-1),(1,0,-1)):
            rows.append(3*s[:,i]+a); cols.append(3*s[:,j]+b); vals.append(sg*kab)
K = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3*N, 3*N))
fixed = set(f['layers/sets/fixed'][:].tolist())
free = np.array([i for i in range(N) if i not in fixed and m[i] > 0])
dof = (3*free[:,None] + np.arange(3)).ravel()
Kf = K[dof][:, dof].tocsc(); Mf = sp.diags(np.repeat(m[free], 3))
t = time.time()
w, v = sla.eigsh(Kf, k=8, M=Mf, sigma=-1e-3, which='LM')
print(sys.argv[1].split('/')[-1], 'nodes', N, 'free', len(free), 'eig s %.1f' % (time.time()-t))
for i in np.argsort(w):
    amp = (v[:, i].reshape(-1, 3)**2).sum(1) * m[free]
    share = {}
    for n in layers:
        sel = np.array([owner[j] == n for j in free])
        share[n] = amp[sel].sum() / amp.sum()
    print('  f %.3f Hz' % (np.sqrt(max(w[i], 0)) / 2 / np.pi), ' '.join('%s %.2f' % (k, v_) for k, v_ in share.items() if v_ > 0.02))
