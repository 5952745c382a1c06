# The recal gateway daemon. On a gateway: map the serial devices, mount a volume for recordings
# and checkpoints, and use host networking (or publish the Zenoh port) so peers/routers reach it:
#   docker run --device /dev/ttyUSB0 -v /var/lib/recal:/data --network host recal \
#       run --port /dev/ttyUSB0 --sensor-id wrist --config /etc/recal/gateway.toml
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY service ./service
COPY configs /etc/recal
RUN pip install --no-cache-dir .
VOLUME ["/data"]
WORKDIR /data
ENTRYPOINT ["recal"]
CMD ["run", "--config", "/etc/recal/gateway.toml"]
