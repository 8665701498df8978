"""The cluster model of issue O: a discrete-event model of a run on W Dask workers.

``trace`` records what a real run's populations cost; ``model`` replays them on virtual
workers with today's executor policies or a candidate design; ``costs`` holds the cost
parameters and ``measured`` the figures they are calibrated and validated against;
``study`` prints the validation and the design study; ``dask_costs`` measures Dask's costs
on this machine. ``python -m benchmarks.cluster_model --help``; docs/benchmarks.md.
"""
