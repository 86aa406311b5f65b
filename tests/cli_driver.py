"""Console scripts run many times without paying their imports each time (a start of ``ns-train`` or a
``scalar-nerf-*`` command costs seconds of imports).

``python -c DRIVER JOBS_JSON`` loads each job's console script (as pip installed it) once, then runs every
job in a forked child with its own argv, working folder, stdout and stderr; the child exits as the
interpreter would (a SystemExit message on stderr, a traceback for any other exception) and its exit
status is written to the job's ``rc`` file. A job: ``{"command": NAME, "args": [...], "stdout": PATH,
"stderr": PATH, "rc": PATH}``, optionally ``"cwd": FOLDER``. What a script prints while it is imported
is not in the jobs' output: a test of that starts the command as a process of its own.
"""

from __future__ import annotations

import textwrap

DRIVER = textwrap.dedent(
    """
    import json, os, sys, traceback
    from importlib.metadata import entry_points

    jobs = json.loads(sys.argv[1])
    scripts = {ep.name: ep for ep in entry_points(group="console_scripts")}
    mains = {name: scripts[name].load() for name in dict.fromkeys(job["command"] for job in jobs)}
    for job in jobs:
        sys.stdout.flush(); sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            os.dup2(os.open(job["stdout"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC), 1)
            os.dup2(os.open(job["stderr"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC), 2)
            if job.get("cwd"):
                os.chdir(job["cwd"])
            sys.argv = [job["command"], *job["args"]]
            code = 0
            try:
                mains[job["command"]]()
            except SystemExit as exit:
                code = exit.code if isinstance(exit.code, int) else (0 if exit.code is None else 1)
                if not isinstance(exit.code, (int, type(None))):
                    print(exit.code, file=sys.stderr)
            except BaseException:
                traceback.print_exc()
                code = 1
            sys.stdout.flush(); sys.stderr.flush()
            os._exit(code)
        _, status = os.waitpid(pid, 0)
        with open(job["rc"], "w") as handle:
            handle.write(str(os.waitstatus_to_exitcode(status)))
    """
)
