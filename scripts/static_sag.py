#!/usr/bin/python3
# The static equilibrium of a built model under gravity (its biphasic springs,
# the fixed set held), optionally with a volume term per tetrahedron of the
# skin layer, E_v = (k_v / 2) (V - V0)^2 / V0 with k_v = FACTOR x the bulk
# modulus of the skin's K1 at nu = 0.45; L-BFGS from the rest state. Prints
# the skin's inverted tetrahedra and grid columns and its mean displacement:
#   scripts/static_sag.py model.h5 FACTOR        (0: springs only)
# A study for the volume term the runtime lacks (docs/runtime.md, Inverted
# layers). numpy, scipy, h5py.
import sys
import time

import h5py
import numpy as np
from scipy.optimize import minimize

from model_arrays import rest_and_masses, springs

if len(sys.argv) != 3:
    raise SystemExit("usage: static_sag.py model.h5 FACTOR")
model = sys.argv[1]; kv_factor = float(sys.argv[2])
f = h5py.File(model, 'r'); L = f['layers']
X0, m = rest_and_masses(f)
N = len(m)
S, K1, K2, R, T = springs(f)
tets = L['skin']['tets'][:]
# the skin's small-strain modulus from its law (spring_law: per class k1 Pa ...)
E_skin = float(L['skin'].attrs['spring_law'][0])
nu = 0.45; Kb = E_skin / (3 * (1 - 2 * nu)); kv = kv_factor * Kb
def vol(X):
    a,b,c,d = (X[tets[:,k]] for k in range(4)); return np.einsum('ij,ij->i', b-a, np.cross(c-a, d-a))/6
V0 = vol(X0)
fixed = np.zeros(N, bool); fixed[f['layers/sets/fixed'][:].astype(int)] = True
free = ~fixed
g = np.array([0, -9.81, 0])
def energy(q):
    X = X0.copy(); X[free] = q.reshape(-1, 3)
    d = X[S[:,1]] - X[S[:,0]]; l = np.linalg.norm(d, axis=1)
    e1 = l - R; e2 = np.maximum(0, l - T)
    E = 0.5*(K1*e1**2).sum() + 0.5*((K2-K1)*e2**2).sum() - (m[:,None]*g[None,:]*X).sum()
    fl = K1*e1 + (K2-K1)*e2
    G = np.zeros((N,3)); u = d / l[:,None] * fl[:,None]
    np.add.at(G, S[:,1], u); np.add.at(G, S[:,0], -u)
    G -= m[:,None]*g[None,:]
    if kv > 0:
        a,b,c,dd = (X[tets[:,k]] for k in range(4)); V = np.einsum('ij,ij->i', b-a, np.cross(c-a, dd-a))/6
        r = (V - V0) / V0; E += 0.5*kv*(V0*r**2).sum()
        coef = kv * r  # dE/dV
        gb = np.cross(c-a, dd-a)/6; gc = np.cross(dd-a, b-a)/6; gd = np.cross(b-a, c-a)/6; ga = -(gb+gc+gd)
        for k, gk in enumerate((ga, gb, gc, gd)): np.add.at(G, tets[:,k], coef[:,None]*gk)
    return E, G[free].ravel()
t0 = time.time()
res = minimize(energy, X0[free].ravel(), jac=True, method='L-BFGS-B', options={'maxiter': 20000, 'maxcor': 30, 'gtol': 1e-12, 'ftol': 1e-15})
X = X0.copy(); X[free] = res.x.reshape(-1, 3)
V = vol(X); inv = (V * np.sign(V0) <= 0).sum()
skin = f['layers/sets/surface_skin'][:].astype(int); fat = f['layers/sets/surface_fat'][:].astype(int)
col = ((X[skin]-X[fat])*(X0[skin]-X0[fat])).sum(1) <= 0
print('kv = %g x K (K = %.0f Pa, E_skin %.0f Pa): %s in %d it, %.0f s; skin tets inverted %d of %d, columns %d of %d, mean skin disp %.2f mm, max |grad| %.2e' % (kv_factor, Kb, E_skin, res.message if isinstance(res.message, str) else res.message.decode(), res.nit, time.time()-t0, inv, len(tets), col.sum(), len(skin), 1e3*np.linalg.norm((X-X0)[skin],axis=1).mean(), np.abs(res.jac).max()))
