"""sphinx-gallery hooks of the pbrdf-cl site (named in ``conf.py`` by their dotted names).

The gallery's figures are drawn by pbrdf-cl's own plot functions: into pyplot figures (``fig=``,
which sphinx-gallery's matplotlib scraper shows), or into PNG files (the paper's figures, written
by :mod:`pbrdf_cl.analysis.paper`). :func:`png_scraper` moves every PNG an example block wrote into
its folder (sphinx-gallery runs an example in the gallery's source folder) to sphinx-gallery's
image paths, and
:func:`clean_outputs` removes the other files an example wrote there (the ``.npz`` and ``.nc``
beside a figure), so that the source folder holds only the examples.
"""
from pathlib import Path

SOURCES = {".py", ".rst", ".txt"}


def png_scraper(block, block_vars, gallery_conf):
    """The PNG files the last block wrote into the example's folder, as sphinx-gallery images."""
    from sphinx_gallery.scrapers import figure_rst
    folder = Path(block_vars["src_file"]).parent
    paths = []
    for png, target in zip(sorted(folder.glob("*.png")), block_vars["image_path_iterator"]):
        png.replace(target)
        paths.append(target)
    return figure_rst(paths, gallery_conf["src_dir"])


def clean_outputs(gallery_conf, fname, when):
    """After each example: remove what it wrote into the gallery's source folder (not its sources)."""
    if when != "after":
        return
    dirs = gallery_conf["examples_dirs"]
    for folder in [dirs] if isinstance(dirs, str) else dirs:
        for path in (Path(gallery_conf["src_dir"]) / folder).iterdir():
            if path.is_file() and path.suffix not in SOURCES:
                path.unlink()
