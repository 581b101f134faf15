"""A team on a robot network: a mission's nodes as processes that talk over Zenoh.

The rover nodes and the base station of a mission on processes
(:mod:`fedmap.mission.network.remote`: the base's orders, the rovers' reports, the same
frames and checks as over Flower) carried by `Zenoh <https://zenoh.io>`_, the middleware of
ROS 2's ``rmw_zenoh``, peer to peer or through routers, with no SuperLink and no process per
message:

* :mod:`~fedmap.zenohnet.session`: a node's Zenoh configuration (where it listens and
  connects, TLS with mutual authentication and access control), and the team's key expressions;
* :mod:`~fedmap.zenohnet.rover`: a rover node (``fedmap node rover``), its node kept in memory;
* :mod:`~fedmap.zenohnet.base`: the base station (``fedmap node base``), the mission clock;
* :mod:`~fedmap.zenohnet.deploy`: ``fedmap mission --deploy zenoh``, a whole team on this machine.

It sits above the Flower adapter so that it shares its Flower-free parts (the base's
journal, the run's files, the processes and certificates); nothing here imports ``flwr``.
"""
