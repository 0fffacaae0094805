"""The initial point cloud format shared by `sampling`, `align` and `train`.

`cloud.npz` holds float32 arrays `points [N,3]`, `colors [N,3]` (RGB in [0,1]),
`normals [N,3]` (unit, into the room; zero for depth points), `u0 [N,3]` (the
initial position the layout regulariser pulls towards; = points) and
`is_layout [N]` (bool). `cloud.ply` holds the same points for viewers.
"""

from __future__ import annotations

from pydantic import BaseModel, Field


class CloudFiles(BaseModel):
    npz: str = Field(description="cloud.npz (points, colors, normals, u0, is_layout)")
    ply: str = Field(description="cloud.ply (positions, normals, colours) for viewers")
    num_points: int = Field(ge=0)
    num_layout_points: int = Field(ge=0)
