"""npe2 writer: displacement field files (``.dvcfield``, or ``.npz``) from the layers the plugin made.

Every field layer the plugin makes (vectors, ``|u|``, components, ZNCC, status, εeq) carries its
:class:`~napari_dvc_correct.engine.fields.field.DisplacementField` in ``metadata["dvc_correct"]["field"]``;
the writer saves that field, not the displayed (subsampled) layer data. Selecting layers of
several fields (e.g. uncorrected and corrected), or a series layer (one field per state after
the first), writes one file per field, named ``STEM_SOURCE.dvcfield`` (``run_corrected``,
``run_state_2_total``). A ``.dvcfield`` file opens in napari with this plugin's reader without a
dialog (:mod:`._reader`); ``.npz`` holds the same contents.
"""

from __future__ import annotations

from pathlib import Path


def write_fields(path: str, layer_data: list[tuple]) -> list[str]:
    """Write the fields behind the selected plugin layers.

    Parameters
    ----------
    path : str
        Target file; ``.dvcfield`` is appended unless it ends in ``.dvcfield`` or ``.npz``.
    layer_data : list of (data, meta, layer_type)
        The selected layers, as napari passes them to a multi-layer writer.

    Returns
    -------
    list of str
        Paths written.

    Raises
    ------
    ValueError
        If none of the layers was made by the plugin from a field.
    """
    from ._reader import is_field_file
    from .io.npz import FIELD_SUFFIX, save_field
    from .layers import field_of, plugin_metadata, series_of, state_source

    fields, sources = [], []
    for _data, meta, _layer_type in layer_data:
        metadata = meta.get("metadata", {})
        source = str((plugin_metadata(metadata) or {}).get("source", "field"))
        series = series_of(metadata)
        if series:  # a series layer: every state after the first, each its own file
            entries = [(f, state_source(source, t)) for t, f in enumerate(series) if t > 0]
        else:
            entries = [(field_of(metadata), source)]
        for field, name in entries:
            if field is not None and not any(field is known for known in fields):
                fields.append(field)
                sources.append(name)
    if not fields:
        names = ", ".join(str(meta.get("name", "?")) for _d, meta, _t in layer_data)
        raise ValueError(
            f"none of the selected layers ({names}) holds a displacement field made by the DVC "
            "plugin; select a displacement, |u|, ZNCC, status or εeq layer"
        )
    target = Path(path)
    suffix = target.suffix.lower()
    if suffix not in (FIELD_SUFFIX, ".npz"):
        target, suffix = target.with_name(target.name + FIELD_SUFFIX), FIELD_SUFFIX
    outs = []
    for source in sources:
        out = target
        if len(fields) > 1:
            safe = "".join(c if c.isalnum() or c == "-" else " " for c in source)
            safe = "_".join(safe.split())  # "state 1 (total)" -> state_1_total
            out = target.with_name(f"{target.stem}_{safe}{suffix}")
        outs.append(out)
    for out in outs:  # never over someone's data (the scans' rock.npz): only over a field file
        if out.exists() and not is_field_file(out):
            raise ValueError(
                f"{out.name} is not a field file (it may hold your scans): choose another name"
            )
    written = []
    for field, out in zip(fields, outs):
        save_field(field, out)
        written.append(str(out))
    return written
