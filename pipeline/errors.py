"""Errors a user can fix. The entry point prints them as one paragraph, without a traceback."""


class PipelineError(Exception):
    """A problem with the input (config, files, arguments), explained in the message."""


class ConfigError(PipelineError):
    """A config value that is not allowed. The message names the key, the value and what is allowed."""


class EstimateLayoutError(PipelineError):
    """A filter's estimate whose arrays do not have the study's layout (filters.base.SingleTargetFilter).
    The message names the variant, its class, the shapes it has and the shapes expected."""


class StorageError(PipelineError):
    """A file or folder the pipeline must write cannot be written (a path under a file, no permission,
    no space, a folder where a file belongs). The message names the path, the OS's reason and the fix."""


def cannot_write(path: object, exc: OSError, what: str = "write") -> StorageError:
    """One paragraph for an OSError met while writing ``path``."""
    reason = exc.strerror or type(exc).__name__
    hint = {
        "EISDIR": f"{path} is a folder where the pipeline keeps a file; move it out of the way",
        "ENOTDIR": "a part of that path is a file, not a folder; choose another paths.artifacts",
        "ENOENT": "a folder on that path cannot be created there (paths.artifacts must be a folder you can write, "
                  "not under /proc or /sys)",
        "EACCES": "you may not write there; choose a paths.artifacts you own",
        "EPERM": "you may not write there; choose a paths.artifacts you own",
        "EROFS": "that file system is read-only; choose another paths.artifacts",
        "ENOSPC": "the disk is full; free space (old runs under <artifacts>/runs, *.rejected cache files) or "
                  "choose another paths.artifacts",
        "EDQUOT": "your disk quota is used up; free space or choose another paths.artifacts",
        "EFBIG": "the file is larger than this process may write (ulimit -f); raise the limit",
    }.get(__import__("errno").errorcode.get(exc.errno or 0, ""), "check that paths.artifacts is a folder you can write")
    return StorageError(f"cannot {what} {path}: {reason}. {hint[0].upper() + hint[1:]}.")
