"""One root exception for the whole project, with a subclass per kind of failure.

The service maps these to ``application/problem+json`` in one handler (see ``service``); the CLI prints
their message and exits non-zero. Keep messages user-facing: they name the field or setting at fault.
"""

from __future__ import annotations

from dataclasses import dataclass


class HoiRefineError(Exception):
    """Root of every error this project raises on purpose."""

    #: HTTP status the service answers with; subclasses override.
    http_status: int = 500
    #: Short problem title for problem+json.
    title: str = "Internal error"


@dataclass(frozen=True)
class FieldProblem:
    """One thing wrong with one input field (``field`` uses dotted paths, e.g. ``hands[0].keypoints``)."""

    field: str
    problem: str

    def __str__(self) -> str:
        return f"{self.field}: {self.problem}"


class InputError(HoiRefineError):
    """The caller's input is wrong; fixing the input fixes the error."""

    http_status = 422
    title = "Invalid input"


class SequenceValidationError(InputError):
    """A sequence failed validation; ``problems`` lists every field at fault."""

    title = "Invalid sequence"

    def __init__(self, problems: list[FieldProblem]) -> None:
        self.problems = list(problems)
        super().__init__("; ".join(str(p) for p in self.problems))

    @classmethod
    def single(cls, field: str, problem: str) -> SequenceValidationError:
        return cls([FieldProblem(field, problem)])


class UnsupportedFormatError(InputError):
    """A file is not in any format we read."""

    title = "Unsupported format"


class UnsupportedMediaTypeError(InputError):
    """A request body of a media type the endpoint does not take (HTTP 415)."""

    http_status = 415
    title = "Unsupported media type"


class ConfigurationError(HoiRefineError):
    """A setting is missing or wrong (the message names the ``HOI_REFINE_*`` variable)."""

    http_status = 500
    title = "Configuration error"


class ManoModelMissingError(ConfigurationError):
    """MANO parameters were given but no MANO model files are configured."""

    http_status = 422
    title = "MANO model not configured"


class NotFoundError(HoiRefineError):
    http_status = 404
    title = "Not found"


class ConflictError(HoiRefineError):
    """The request conflicts with the current state (e.g. deleting a running job)."""

    http_status = 409
    title = "Conflict"


class IdempotencyMismatchError(InputError):
    """An Idempotency-Key was reused with a different payload."""

    title = "Idempotency-Key reused with another payload"


class LimitExceededError(HoiRefineError):
    """A configured limit was hit; ``retry_after`` seconds, when set, says when to try again."""

    http_status = 429
    title = "Limit exceeded"

    def __init__(self, message: str, retry_after: int | None = None) -> None:
        super().__init__(message)
        self.retry_after = retry_after


class PayloadTooLargeError(HoiRefineError):
    http_status = 413
    title = "Payload too large"


class AuthenticationError(HoiRefineError):
    http_status = 401
    title = "Unauthorized"


class LeaseLostError(HoiRefineError):
    """A worker's lease on a job is gone (expired and requeued, or cancelled); it must stop writing."""

    http_status = 409
    title = "Lease lost"


class JobCancelledError(HoiRefineError):
    """Raised inside a running job when its cancellation flag is seen."""

    http_status = 409
    title = "Job cancelled"


class DatabaseUnavailableError(HoiRefineError):
    http_status = 503
    title = "Database unavailable"


class ResultMismatchError(HoiRefineError):
    """``verify`` re-simulated a result and the object trajectory differs."""

    title = "Result does not reproduce"


class ApiError(HoiRefineError):
    """The hoi-refine service answered a client request with an error it will not recover from by retrying."""

    def __init__(self, message: str, status: int | None = None, problem: dict[str, object] | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.problem = dict(problem or {})


class InvalidRequestError(SequenceValidationError):
    """A request parameter other than the sequence is wrong (e.g. ``page_token``); ``problems`` names each."""

    title = "Invalid request"
