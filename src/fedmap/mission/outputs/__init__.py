"""What a mission leaves: ``metrics.json``, ``report.md`` and plots (``report``), an MCAP
recording and live view (``recording``), ROS 2 bags (``bag``) and map files (``maps_out``).
"""
