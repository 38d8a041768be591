"""The built-in Hydra configs, shipped as the package ``lnf.conf`` (pyproject.toml maps this folder there).

The entry points read them with ``@hydra.main(config_path="pkg://lnf.conf")``, which works in an editable and in
a regular install and from any directory; ``--config-dir DIR`` adds a folder of your own on top. This file only
makes the folder a package (Hydra's ``pkg://`` configs need one); keep the configs themselves as ``.yaml`` files.
"""
