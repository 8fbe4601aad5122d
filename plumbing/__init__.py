"""What datagen and gns share and neither owns: one-line error classes (plumbing.errors), atomic
writes and checks on outputs (plumbing.files), and the TOML presets with their value rules
(plumbing.tomlconfig)."""
