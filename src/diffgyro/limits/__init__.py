"""Pass/fail of every device for a production line: ``--limits FILE.toml``.

A limits file (:mod:`.spec`) bounds any numeric field of a device's record by
its dotted path (``heldout_rms``, ``noise_floor``, ``params.*.bias_poly(1).c0``,
``motion.moving_fraction``) and requires text fields (``status = "ok"``);
figures a record does not hold by default are computed when a limit asks for
them (:mod:`.figures`: Allan read-outs of the fit residual, the bias and its
temperature coefficient over the calibrated range). Each device gets ``pass``
or ``fail`` with the limits it broke and by how much; a batch its yield and the
list of rejected units (:mod:`.check`).
"""

from __future__ import annotations

from ._check import broken_text, check, check_model, lookup, summary, unmatched
from ._figures import add_figures, bias_figures, residual_allan
from ._spec import Limit, Limits, from_dict, load, split_path

__all__ = ["load", "check", "check_model", "Limits", "Limit", "add_figures", "bias_figures",
           "broken_text", "from_dict", "lookup", "residual_allan", "split_path", "summary",
           "unmatched"]
