"""``/v1/replicas``: the alive replicas and the live rigs each estimates, as seen from this one."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends
from pydantic import BaseModel, Field

from ..deps import LiveDep, bearer_scheme
from ..schemas import error_responses

router = APIRouter(prefix="/v1/replicas", tags=["rigs"], dependencies=[Depends(bearer_scheme)],
                   responses=error_responses(401, 403))


class ReplicaOut(BaseModel):
    replica: str = Field(description="the replica's id (its POSECAL_REPLICA_ID)")
    rigs: list[str] = Field(description="rigs heard on the network (within rig_expiry_s) that rendezvous "
                            "hashing gives it")


class ReplicasOut(BaseModel):
    replica: str = Field(description="this replica's id")
    enabled: bool = Field(description="replicas on: rigs are shared by the alive replicas (off: this one "
                          "estimates every rig it hears)")
    active: bool = Field(description="false while another session with this id (and a smaller Zenoh id) "
                         "is alive: that one estimates, this one nothing")
    others_with_this_id: list[str] = Field(description="Zenoh session ids of other sessions using this id")
    replicas: list[ReplicaOut] = Field(description="alive replicas (this one included), by id")


@router.get("", response_model=ReplicasOut)
def list_replicas(live: LiveDep) -> dict[str, Any]:
    """Which replica estimates which rig, as this replica sees it (every replica computes the
    same from the same membership: docs/SERVICE.md, "Several replicas")."""
    return live.replica_view()
