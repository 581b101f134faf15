"""What fedmap learns from missions, offline, to ship or to share: each runs missions
(:mod:`fedmap.mission`) and trains on what their rovers mapped.

* :mod:`~fedmap.training.coderprior`: the predictive coder's learned initial state
  (``fedmap/weights/cell_prior.npz``);
* :mod:`~fedmap.training.predictorprior`: the map predictor's offline training data and its
  shipped weights;
* :mod:`~fedmap.training.predictorfed`: the predictor fine-tuned across sites with FedAvg
  (``fedmap federate-predictor``, in process or on Flower).

None of it runs during a mission: a mission only reads what these wrote.
"""
