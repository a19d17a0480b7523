"""Turn a ``POST /v1/jobs`` request into a validated sequence, its options and the payload to queue.

Two forms (issue #4): a JSON body (the native JSON sequence with an ``options`` object), or multipart with
a ``sequence`` file part (native NPZ, or a DexYCB development NPZ when ``HOI_REFINE_YCB_DIR`` is set) and an
``options`` JSON part. Every problem is reported with its field; the frame limit names ``object_pose``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import FormData, UploadFile
from starlette.requests import Request

from common.errors import (
    ConfigurationError,
    FieldProblem,
    InvalidRequestError,
    PayloadTooLargeError,
    UnsupportedMediaTypeError,
)
from common.job_options import JobOptions
from common.safe_text import shown
from common.sequence import Sequence
from common.sequence_io import sequence_from_json_dict, sequence_from_npz_bytes, sequence_to_npz_bytes
from common.settings import Settings
from service.problems import validation_problems
from service.schemas import JobCreate

MULTIPART_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "sequence": {
            "type": "string", "format": "binary",
            "description": "a native sequence NPZ (a DexYCB development NPZ where the server sets HOI_REFINE_YCB_DIR)",
        },
        "options": {"$ref": "#/components/schemas/JobOptions", "description": "a JSON part (see encoding)"},
        "batch_id": {
            "type": "string", "minLength": 1, "maxLength": 32,
            "description": "submit into this batch (POST /v1/batches)",
        },
    },
    "required": ["sequence"],
    "additionalProperties": False,  # another part is refused, naming it (``_read_form``)
}  # fmt: skip
#: The options part is JSON, which a generated client learns from the part's encoding.
MULTIPART_ENCODING: dict[str, Any] = {"options": {"contentType": "application/json"}}


@dataclass(frozen=True)
class Submission:
    sequence: Sequence
    options: JobOptions
    #: The sequence as native NPZ bytes: what the queue stores and the worker reads.
    payload: bytes
    #: The batch to submit into, or None.
    batch_id: str | None = None


def _invalid(problems: list[FieldProblem]) -> InvalidRequestError:
    return InvalidRequestError(problems)


def _prefixed(exc: ValidationError, prefix: str) -> list[FieldProblem]:
    return [FieldProblem(f"{prefix}.{p.field}" if p.field != "body" else prefix, p.problem)
            for p in validation_problems(exc.errors())]  # fmt: skip


async def read_submission(request: Request, settings: Settings) -> Submission:
    """The request's sequence and options, validated; every problem is a 4xx naming its field.

    The body's size is enforced while it streams (``service.middleware.BodySizeLimit``); a JSON body has
    its own, smaller limit because parsing it costs far more memory per byte than an NPZ upload.
    """
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if content_type == "application/json":
        body = await _read_json_body(request, settings.max_json_request_bytes)
        seq, options, batch_id = await run_in_threadpool(_from_json, body, settings)
    elif content_type == "multipart/form-data":
        blob, options, batch_id = await _read_multipart(request, settings)
        seq = await run_in_threadpool(_from_npz, blob, settings)
    else:
        raise UnsupportedMediaTypeError(
            f"Content-Type {shown(content_type or '(none)')} is not accepted: send application/json or "
            "multipart/form-data"
        )
    payload = await run_in_threadpool(sequence_to_npz_bytes, seq)
    return Submission(seq, options, payload, batch_id)


async def _read_json_body(request: Request, limit: int) -> bytes:
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise PayloadTooLargeError(
                f"a JSON submission may be at most {limit} bytes (HOI_REFINE_MAX_JSON_REQUEST_BYTES); "
                "send large sequences as NPZ (multipart/form-data)"
            )
        chunks.append(chunk)
    return b"".join(chunks)


def _from_json(body: bytes, settings: Settings) -> tuple[Sequence, JobOptions, str | None]:
    try:
        # pydantic parses the bytes straight into the model (no intermediate Python objects); NaN and
        # Infinity are refused by the models' allow_inf_nan=False, too-deep nesting by its recursion limit.
        # Strict: a number is a JSON number ("fps": "30" is refused, as the schema says), a boolean a JSON
        # boolean; only an integer is taken where a float is asked for.
        parsed = JobCreate.model_validate_json(body, strict=True)
    except ValidationError as exc:
        raise _invalid(validation_problems(exc.errors())) from exc
    seq_doc = parsed.model_dump(exclude={"options", "batch_id"}, exclude_none=True)
    return sequence_from_json_dict(seq_doc, max_frames=settings.max_frames), parsed.options, parsed.batch_id


async def _read_multipart(request: Request, settings: Settings) -> tuple[bytes, JobOptions, str | None]:
    # The context closes the spooled temporary files of the parts (else each request leaks one until GC).
    async with request.form(max_files=1, max_fields=10, max_part_size=1024 * 1024) as form:
        return await _read_form(form)


async def _read_form(form: FormData) -> tuple[bytes, JobOptions, str | None]:
    unknown = sorted({key for key in form if key not in MULTIPART_SCHEMA["properties"]})
    if unknown:
        raise _invalid([FieldProblem(shown(key, 40), "unknown part; a multipart submission holds sequence, options and "
                                     "batch_id") for key in unknown[:5]])  # fmt: skip
    seq_part = form.get("sequence")
    if seq_part is None:
        raise _invalid([FieldProblem("sequence", "is required (a file part holding the sequence NPZ)")])
    blob = await seq_part.read() if isinstance(seq_part, UploadFile) else seq_part.encode()
    raw_options = form.get("options")
    if isinstance(raw_options, UploadFile):
        raw_options = (await raw_options.read(1024 * 1024 + 1)).decode(errors="replace")
    try:
        options = JobOptions.model_validate_json(raw_options, strict=True) if raw_options else JobOptions()
    except ValidationError as exc:
        raise _invalid(_prefixed(exc, "options")) from exc
    batch_id = form.get("batch_id")
    if batch_id is not None and (not isinstance(batch_id, str) or not 0 < len(batch_id) <= 32):
        raise _invalid([FieldProblem("batch_id", "must be a batch id (text, at most 32 characters)")])
    return blob, options, batch_id


def _from_npz(blob: bytes, settings: Settings) -> Sequence:
    if blob.lstrip(b"\xef\xbb\xbf \t\r\n")[:1] in (b"{", b"["):
        # A JSON sequence sent as the file part: say how to send it rather than that it is no zip file.
        raise _invalid([FieldProblem("sequence", "holds JSON, not an NPZ file: send a JSON sequence as the request "
                                     "body itself (Content-Type: application/json, the job options as its "
                                     "\"options\" member), or the file part as a native or DexYCB NPZ")])  # fmt: skip
    try:
        seq = sequence_from_npz_bytes(blob, limits=settings.parse_limits())
    except ConfigurationError as exc:
        # A DexYCB file names its YCB object; without HOI_REFINE_YCB_DIR this server cannot read it. The
        # message names the setting, never this server's folders.
        raise _invalid([FieldProblem("sequence", "this server cannot read DexYCB development files (its "
                                     "administrator has not set HOI_REFINE_YCB_DIR)")]) from exc  # fmt: skip
    seq.meta.pop("source_path", None)  # a server path; an upload has none
    return seq
