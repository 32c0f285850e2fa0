"""Generated protobuf/gRPC modules (do not edit; see `haa.pb.generate`)."""
