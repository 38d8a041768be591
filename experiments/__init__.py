"""The benchmark studies, run as `python -m experiments.<study>` from the repository root; not installed with lnf."""
