"""reconstruct: reflection removal from spike streams (harmonic fit, RIR, LS/ridge/IRLS/RWPS solvers, PolSpikeNet).

Third floor: imports :mod:`polinfra`, :mod:`polphysics` and :mod:`spike_sim`, never
:mod:`generator`, so it runs on real captures.
"""
