"""The package's version, in a module of its own: the modules that write it into a store
(``pbrdf_cl_version``) or print it (``pbrdf-cl --version``) import it from here, never from the
package root, and ``setup.cfg`` reads it from here (``version = attr: pbrdf_cl.version.__version__``)."""

__version__ = "0.1.0"
