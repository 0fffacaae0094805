"""The base of every stage's parameters (stages/<name>.py `Params`)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, model_validator

#: How a setting sets a working image size, marked in its Field as json_schema_extra={"pixels": KIND}.
PIXEL_KINDS = {
    "panorama_height": lambda v: (v, 2 * v),  # an equirectangular panorama H x 2H
    "square": lambda v: (v, v),  # a perspective crop S x S
    "hw": lambda v: (v[0], v[1]),  # an explicit [H, W]
}
#: Field json_schema_extra key of a setting whose value names a file (pipeline/settings.py).
NAMES_FILE = {"names_file": True}


def field_extra(field) -> dict:
    return field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}


class StageParams(BaseModel):
    """Unknown parameters are refused (a typo is not silently ignored), and so is a float that is
    not finite: `lr=inf`, `1e400` (YAML reads it as inf) or `background: [.nan, 0, 0]` would only
    train a model of NaNs, so every float setting, nested in lists and tuples too, is checked when
    settings are validated. A setting that sets a working image size (marked `pixels`) is held to
    the image limit (runfs/limits.py) before anything of that size is allocated."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @model_validator(mode="after")
    def _sizes_within_the_pixel_limit(self):
        from runfs.limits import pixels_problem

        for name, field in type(self).model_fields.items():
            kind, value = field_extra(field).get("pixels"), getattr(self, name)
            if kind is None or not isinstance(value, int | tuple | list):
                continue  # None or a named size ('train', 'image'): the images' own, already checked
            h, w = PIXEL_KINDS[kind](value)
            problem = pixels_problem(h, w)
            if problem:
                raise ValueError(f"{name} {list(value) if kind == 'hw' else value}: the working image "
                                 f"{problem} (raise --max-megapixels if you mean it)")
        return self
