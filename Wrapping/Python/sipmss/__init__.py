"""SIPMSS: storage-independent simplification of huge triangle meshes for VTK and ParaView.

    from sipmss import vtkSIPMSSCluster, vtkSIPMSSDecimate

Works with the VTK the module was built against (ParaView's pvpython / python3-paraview, or
Debian's VTK 9.1 vtkmodules). Import vtkmodules (or paraview) first if you mix with other VTK code.
"""
from .sipmssFilters import *  # noqa: F401,F403
from .sipmssFilters import __doc__ as _wrapped_doc  # noqa: F401


