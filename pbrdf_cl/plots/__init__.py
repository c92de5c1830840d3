"""Every figure (matplotlib): fits (``fit``), joint fits (``joint``), two-axis maps (``maps``), the
paper's figures (``paper``), image-fit maps (``images``), sensitivity maps (``sensitivity``),
measurement designs (``design``), the explorer's view (``explore``); what they share (``common``:
the figure drawn into, writing it, the inputs' axis labels).

A function that draws one panel takes ``ax=`` and returns the axes; one that draws several takes
``fig=`` (a figure or subfigure) and returns the figure.  Without them it makes its own figure (a
plain ``matplotlib.figure.Figure``: the package never chooses matplotlib's backend), and it writes
a file only when given a path."""
