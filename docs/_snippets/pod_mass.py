import numpy as np, scipy.sparse as sp, streamsvd as ss
n = 2000; M = sp.diags(np.full(n, 1 / n))                 # a mass matrix (SPD)
t = np.linspace(0, 1, n)[:, None]
sc = ss.StreamCompressor(n, inner=M, target_error=1e-4, error_measure="mean_l2")
for k in range(20):                                       # 20 blocks of 50 snapshots
    s = np.linspace(k, k + 1, 50)[None, :]
    sc.absorb(np.sin(np.pi * t * s) + np.exp(-s) * t**2)
sc.finalize()
print(sc.rank, sc.amplitudes[:3], sc.error_bound, sc.target_met)  # ||A - U V^T||_M <= error_bound
U = sc.left_vectors                                       # U^T M U = I
