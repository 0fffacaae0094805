"""Artifact of the `union` stage: the merged floor plan in the world frame."""

from __future__ import annotations

from pydantic import BaseModel, Field

Point2 = tuple[float, float]


class Room(BaseModel):
    polygon: list[Point2] = Field(description="Outer ring in world (x, z) metres, counter-clockwise from above.")
    holes: list[list[Point2]] = Field(default_factory=list)
    floor_y: float = Field(description="World y of the floor (y points down).")
    ceiling_y: float = Field(description="World y of the ceiling (< floor_y).")
    views: list[str] = Field(description="Views whose floor plans merged into this room.")


class UnionOutput(BaseModel):
    rooms: list[Room] = Field(description="Connected components of the union of per-view floor plans.")
    floor_plan: str = Field(description="floor_plan.json: the same rooms, plus per-view polygons.")
    drawing: str = Field(description="floor_plan.png: the plan with camera positions.")
    area_m2: float
