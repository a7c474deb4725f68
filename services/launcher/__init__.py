"""The launcher: fleet manifests as data, process supervision, run directories and reports."""
