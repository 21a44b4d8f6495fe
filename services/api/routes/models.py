"""GET /models/{id}: one detector ω."""

from fastapi import APIRouter

from services import queries
from services.api.deps import ModelId, SessionDep, read_with
from services.api.schemas import NOT_FOUND, ModelDetail

router = APIRouter(prefix="/models", tags=["models"])


@router.get("/{model_id}", response_model=ModelDetail, responses=NOT_FOUND)
async def model_detail(model_id: ModelId, session: SessionDep) -> ModelDetail:
    """One ω: its stage, k, parent ω_in, training and its evaluation."""
    return await read_with(session, queries.model_detail, model_id)
