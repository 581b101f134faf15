"""The named methods, as data: one TOML file per preset (read by :mod:`fedmap.config`)."""
