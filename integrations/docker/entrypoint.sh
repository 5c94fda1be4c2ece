#!/bin/sh
# Container entry point. No arguments: watch the printer of $LAYERWATCH_PRINTER with the camera of
# $LAYERWATCH_CAMERA, the job config and camera model from $LAYERWATCH_CONFIG_DIR (/config), the history
# in $LAYERWATCH_DB (/data/history.db). With arguments: run that layerwatch verb instead
# (e.g. `serve --db /data/history.db --host 0.0.0.0`).
set -eu
if [ "$#" -gt 0 ]; then
    exec layerwatch "$@"
fi
conf="${LAYERWATCH_CONFIG_DIR:-/config}"
if [ -z "${LAYERWATCH_PRINTER:-}" ] || [ -z "${LAYERWATCH_CAMERA:-}" ]; then
    echo "error: set LAYERWATCH_PRINTER (e.g. moonraker://printer.local:7125) and LAYERWATCH_CAMERA (e.g. http://printer.local/webcam/?action=snapshot) in the --env-file." >&2
    exit 2
fi
for f in "$conf/camera.toml" "$conf/layerwatch.toml"; do
    if [ ! -r "$f" ]; then
        echo "error: $f not found; mount the folder holding camera.toml and layerwatch.toml at $conf (-v \"\$PWD/config:$conf:ro\")." >&2
        exit 2
    fi
done
exec layerwatch monitor --follow --printer "$LAYERWATCH_PRINTER" --camera "$LAYERWATCH_CAMERA" \
    --camera-model "$conf/camera.toml" --config "$conf/layerwatch.toml" --history "${LAYERWATCH_DB:-/data/history.db}" --keep-mb "${LAYERWATCH_KEEP_MB:-2000}"
