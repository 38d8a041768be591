"""The finite-element reference of elastic bodies, assembled by scikit-fem: hyperelastic materials
(:mod:`lnf.fem.materials`), bodies on any mesh of linear cells (:mod:`lnf.fem.body`) and their time stepping
(:mod:`lnf.fem.time_stepping`)."""
from lnf.fem.body import ElasticBody, box_mesh, from_meshio, read_mesh
from lnf.fem.materials import MATERIALS, HyperelasticMaterial, NeoHookean, StVenantKirchhoff, get_material, lame
from lnf.fem.time_stepping import implicit_midpoint, verlet

__all__ = ["ElasticBody", "box_mesh", "from_meshio", "read_mesh", "MATERIALS", "HyperelasticMaterial", "NeoHookean",
           "StVenantKirchhoff", "get_material", "lame", "implicit_midpoint", "verlet"]
