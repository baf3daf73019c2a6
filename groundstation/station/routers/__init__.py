"""One APIRouter per API resource; routes translate HTTP to hub calls and nothing more."""
