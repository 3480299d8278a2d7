# One image for every msk-live node; docker-compose.yml picks the command.
FROM python:3.11-slim
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1
# libusb for Xsens USB discovery (pyusb); the OpenSim extra is not needed at run time.
RUN apt-get update && apt-get install -y --no-install-recommends libusb-1.0-0 && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY msk_core ./msk_core
COPY drivers ./drivers
COPY services ./services
COPY recordings ./recordings
RUN pip install --no-cache-dir .
# the wire schema's Python code (msk_pb2) made here, once in /app (msk live starts its nodes with python -m from the
# working folder) and once in the installed package (the msk command; from / so that /app is not on the path)
RUN python -c "import services.transport.schemas" && cd / && python -c "import services.transport.schemas"
ENTRYPOINT ["msk"]
CMD ["--help"]
