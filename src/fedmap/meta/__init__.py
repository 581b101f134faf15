"""Meta-initialisation: the empty-map prior, Reptile over map collections, the Table I ablation.

``prior``        theta_0: the network fitted to an all-UNKNOWN map.
``reptile``      the Reptile update and the meta-training loop (seeded, resumable).
``collections``  map collections: categories of maps (built-in Earth-like, folders).
``ablation``     Table I: PSNR after N steps from random / empty / meta initialisations.
``shipped``      the meta-initialised weights that ship with the package.
"""
