"""Every figure (matplotlib, Agg backend): fits (``fit``), two-axis maps (``maps``), the paper's
figures (``paper``), image-fit maps (``images``), sensitivity maps (``sensitivity``), measurement
designs (``design``); what they share (``common``: pyplot, the inputs' axis labels)."""
