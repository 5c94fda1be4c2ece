# layerwatch in a container: `layerwatch monitor` by default, `layerwatch serve ...` for the dashboard.
# Use: docs/setup.md, "Run as a service". Build from the repository root: docker build -t layerwatch .
#
# docker run -d --restart unless-stopped -v "$PWD/config:/config:ro" -v layerwatch-data:/data \
#     --env-file layerwatch.env layerwatch
# with LAYERWATCH_PRINTER, LAYERWATCH_CAMERA and the API key (LAYERWATCH_MOONRAKER_KEY or
# LAYERWATCH_OCTOPRINT_KEY) in layerwatch.env, and layerwatch.toml + camera.toml in ./config.

FROM python:3.11-slim AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
COPY pyproject.toml README.md ./
COPY src ./src
RUN python -m venv /opt/layerwatch \
 && /opt/layerwatch/bin/pip install '.[web,notify,fast]'

FROM python:3.11-slim
# a fixed non-root uid/gid, so a bind-mounted /data can be chowned to it on the host
RUN groupadd --system --gid 10001 layerwatch \
 && useradd --system --uid 10001 --gid layerwatch --home-dir /data --shell /usr/sbin/nologin layerwatch \
 && install -d -o layerwatch -g layerwatch -m 0750 /data \
 && install -d -m 0755 /config
COPY --from=build /opt/layerwatch /opt/layerwatch
COPY integrations/docker/healthcheck.py integrations/docker/entrypoint.sh /opt/layerwatch/
ENV PATH=/opt/layerwatch/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    MPLCONFIGDIR=/tmp/matplotlib \
    NUMBA_CACHE_DIR=/tmp/numba \
    LAYERWATCH_DB=/data/history.db
USER layerwatch
WORKDIR /data
VOLUME ["/data"]
EXPOSE 8765
# monitor: the process is alive and the history database opens; serve: the dashboard answers
HEALTHCHECK --interval=60s --timeout=10s --start-period=120s --retries=3 \
    CMD ["python", "/opt/layerwatch/healthcheck.py"]
# no arguments: `layerwatch monitor` on $LAYERWATCH_PRINTER / $LAYERWATCH_CAMERA; arguments: that verb.
# exec form, and the script execs layerwatch: it is PID 1, so `docker stop` (SIGTERM) stops it cleanly
ENTRYPOINT ["/opt/layerwatch/entrypoint.sh"]
CMD []
