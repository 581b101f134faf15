"""Meta-initialisation: Reptile over map collections and the Table I ablation.

``reptile``      the Reptile update and the meta-training loop (seeded, resumable).
``collections``  map collections: categories of maps (built-in Earth-like, folders).
``ablation``     Table I: PSNR after N steps from random / empty / meta initialisations.

The starting points themselves (random, the empty-map prior, the shipped meta-init) are
:mod:`fedmap.nets.init`.
"""
