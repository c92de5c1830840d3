"""(see the package docstring of pbrdf_cl.fitting)"""
