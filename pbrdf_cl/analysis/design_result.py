"""The result of a measurement design (:func:`pbrdf_cl.design`): :class:`DesignResult`, its
summary table and its Dataset."""
from __future__ import annotations

import numpy as np

from ..compute.dense import PARAMETERS
from ..results import Result
from .instruments import instrument_table, instrument_variables

GEOMETRY = ("theta_i", "theta_r", "phi")


def _kd_meaning(result):
    """What a design's ``kd`` is: the ratio kd/ks, or the absolute kd where ks is fixed."""
    fx = result.get("fixed", {})
    return f"kd is absolute, ks fixed at {fx['ks']:g}" if "ks" in fx else "kd is kd/ks"


class DesignResult(Result):
    """The chosen measurements and their predicted 95% interval widths (attribute-access dict).

    ``theta_i``, ``theta_r``, ``phi`` (degrees): the chosen geometries; ``ci95_width``: dict
    parameter -> predicted width (the median over the materials of a box);
    ``ci95_width_reference`` the same for ``reference`` (dict of geometry arrays);
    ``comparisons``: name -> dict(widths, n_points, description, undetermined); ``information``:
    each candidate's value at the final design (shaped as the candidate grid,
    ``information_axes``); ``undetermined`` (``undetermined_reference``): the free parameters the
    chosen (reference) set does not determine, whose predicted interval spans their whole bounds
    (their width is then the bound range); ``notes``: sentences on what the design cannot do;
    ``criterion``, ``criterion_value``, ``criterion_greedy``, ``free``, ``target``, ``noise``, ...;
    with ``instrument=``: ``instruments`` (each one's name, description, quantities, states,
    noise, channels per geometry; the first is the design's) and ``instrument_comparisons``
    ("chosen", "reference" -> instrument -> dict(widths, se, undetermined, n_points, channels):
    every instrument at the same geometries, ``se`` the standard errors before clipping);
    :func:`pbrdf_cl.plots.design.plot_design` draws it.
    """

    @property
    def compared(self):
        """The parameters of the comparisons' columns (of :meth:`summary`, :meth:`to_dataset` and the
        figure): the free ones, and ks after them where ks is not free (an intensity column frees it)."""
        return list(self.free) + ([] if "ks" in self.free else ["ks"])

    def summary(self):
        """A readable text table of the predicted widths."""
        names = self.compared
        ins = self.get("instruments") or [None]
        noise = (f"DOP noise {self.noise:g}" if ins[0] is None else
                 f"instrument {ins[0]['name']} ({ins[0]['description']}), noise {ins[0]['noise']:g} per quantity")
        lines = [f"measurement design: {len(self.theta_i)} measurements, criterion {self.criterion} on "
                 f"{', '.join(self.target)}; {noise}"
                 + (f", F00 relative noise {self.intensity_noise:g}" if self.intensity else "")
                 + (f"; median over {self.n_materials} materials" if self.n_materials > 1 else ""),
                 f"  criterion: greedy {self.criterion_greedy:.6g} -> exchange {self.criterion_value:.6g} "
                 f"({self.swaps} swaps; reference {self.criterion_reference:.6g}); {self.seconds:.2f} s",
                 "", f"predicted 95% interval widths ({_kd_meaning(self)})"]
        head = f"  {'measurement set':<44s}{'points':>7s}" + "".join(f"{n:>10s}" for n in names)
        lines.append(head)
        for c in self.comparisons.values():
            w, u = c["widths"], c.get("undetermined", ())
            lines.append(f"  {c['description'][:43]:<44s}{c['n_points']:>7d}"
                         + "".join(f"{'undet.':>10s}" if n in u else f"{w[n]:>10.4g}" if n in w else f"{'-':>10s}"
                                   for n in names))
        if any(c.get("undetermined") for c in self.comparisons.values()):
            lines.append("  undet.: undetermined, the predicted interval spans the whole bounds (the data do not "
                         "determine the parameter)")
        lines += [f"note: {n}" for n in self.get("notes", ())]
        lines += instrument_table(self)
        lines += ["", "chosen geometries (theta_i, theta_r, phi) [deg]:"]
        pts = [f"({a:g}, {b:g}, {c:g})" for a, b, c in zip(self.theta_i, self.theta_r, self.phi)]
        for i in range(0, len(pts), 6):
            lines.append("  " + " ".join(pts[i:i + 6]))
        return "\n".join(lines)

    def to_dataset(self):
        """The result as an ``xarray.Dataset`` (``to_netcdf`` saves it)."""
        import xarray as xr
        deg = {"units": "deg"}
        data = {g: xr.Variable(("measurement",), self[g], deg) for g in GEOMETRY}
        data.update({f"reference_{g}": xr.Variable(("reference_measurement",), self.reference[g], deg)
                     for g in GEOMETRY})
        data.update({
            "ci95_width": xr.Variable(("parameter",), [self.ci95_width[n] for n in self.free],
                                      {"long_name": "predicted 95% interval width, chosen set"}),
            "ci95_width_reference": xr.Variable(("parameter",), [self.ci95_width_reference[n] for n in self.free],
                                                {"long_name": "predicted 95% interval width, reference set"}),
            "undetermined": xr.Variable(("parameter",), np.array([n in self.undetermined for n in self.free], np.int8),
                                        {"long_name": "1 where the chosen set does not determine the parameter "
                                                      "(its predicted interval spans the whole bounds)"}),
            "undetermined_reference": xr.Variable(
                ("parameter",), np.array([n in self.undetermined_reference for n in self.free], np.int8),
                {"long_name": "1 where the reference set does not determine the parameter"}),
        })
        comp = list(self.comparisons)
        allp = self.compared
        data["comparison_width"] = xr.Variable(
            ("comparison", "parameter_all"),
            [[self.comparisons[c]["widths"].get(n, np.nan) for n in allp] for c in comp],
            {"long_name": "predicted 95% interval width (NaN: not free)"})
        data["comparison_undetermined"] = xr.Variable(
            ("comparison", "parameter_all"),
            np.array([[n in self.comparisons[c].get("undetermined", ()) for n in allp] for c in comp], dtype=np.int8),
            {"long_name": "1 where the predicted interval spans the whole bounds: the parameter is undetermined"})
        data["comparison_points"] = xr.Variable(("comparison",), [self.comparisons[c]["n_points"] for c in comp])
        data["comparison_description"] = xr.Variable(("comparison",), [self.comparisons[c]["description"]
                                                                        for c in comp])
        info_dims = tuple(f"candidate_{n}" for n in self.information_axes) or ("candidate",)
        data["information"] = xr.Variable(info_dims, self.information, {"long_name": self.information_label,
                                                                        "units": "1"})
        coords = {"parameter": list(self.free), "parameter_all": allp, "comparison": comp}
        if self.get("instruments"):
            more, more_coords = instrument_variables(self)
            data.update(more)
            coords.update(more_coords)
        for n, v in self.information_axes.items():
            coords[f"candidate_{n}"] = xr.Variable((f"candidate_{n}",), v, deg)
        if self.n_materials > 1:
            data["materials"] = xr.Variable(("material", "model_parameter"),
                                            np.stack([self.materials[n] for n in PARAMETERS], axis=1))
            data["ci95_width_materials"] = xr.Variable(("material", "parameter"),
                                                       np.stack([self.ci95_width_materials[n] for n in self.free],
                                                                axis=1))
            coords["model_parameter"] = list(PARAMETERS)
        attrs = dict(criterion=self.criterion, target=",".join(self.target), noise=self.noise,
                     intensity=int(self.intensity), intensity_noise=self.intensity_noise,
                     criterion_value=self.criterion_value, criterion_greedy=self.criterion_greedy,
                     criterion_reference=self.criterion_reference, swaps=self.swaps,
                     n_materials=self.n_materials, shadowing=self.shadowing, engine=self.engine,
                     seconds=round(self.seconds, 3), notes=" | ".join(self.get("notes", ())))
        for n, (lo, hi) in self.bounds.items():
            attrs[f"bounds_{n}"] = [lo, hi]
        for n, v in self.material.items():
            attrs[f"material_{n}"] = v
        return xr.Dataset(data, coords=coords, attrs=attrs)
