"""The presets (TOML): the model and scene configurations, shipped with the package.

In a checkout they are read from here; installed from a wheel, the same files are the package
`rigid_gns_configs` (see pyproject.toml). Look them up with plumbing.config_dir().
"""
