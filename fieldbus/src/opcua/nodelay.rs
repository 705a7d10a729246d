//! The client's TCP connection with Nagle's algorithm off.
//!
//! async-opcua's own connector leaves it on. A bridge sends small requests back to back
//! (the client's Publish requests, then the period's Write): with Nagle on, the Write
//! waits for the acknowledgement of the Publish before it leaves, and the server, which
//! has nothing to answer a Publish with yet, delays that acknowledgement (40 ms on Linux).
//! Measured against asyncua with a subscription: one Write in ten took 38 ms instead of
//! under 1. With Nagle off, each request leaves when it is written.

use std::sync::Arc;

use opcua::client::transport::SecureChannelState;
use opcua::client::transport::{
    Connector, OutgoingMessage, StreamConnection, StreamConnector, TcpTransport,
    TransportConfiguration,
};
use opcua::client::ConnectionSource;
use opcua::core::comms::tcp_codec::TcpCodec;
use opcua::core::comms::url::hostname_port_from_url;
use opcua::types::{DecodingOptions, EndpointDescription, Error, StatusCode};
use tokio::io::{ReadHalf, WriteHalf};
use tokio::net::TcpStream;
use tokio_util::codec::FramedRead;

/// Sessions connect through [`NoDelayConnector`].
pub(crate) struct NoDelay;

impl ConnectionSource for NoDelay {
    type Builder = NoDelayConnector;

    fn get_connector(&self, endpoint: &EndpointDescription) -> Result<NoDelayConnector, Error> {
        Ok(NoDelayConnector {
            endpoint: endpoint.clone(),
        })
    }
}

/// async-opcua's TCP connector, but for `TCP_NODELAY` on the socket.
pub(crate) struct NoDelayConnector {
    endpoint: EndpointDescription,
}

impl Connector for NoDelayConnector {
    type Transport = TcpTransport;

    async fn connect(
        &self,
        channel: Arc<SecureChannelState>,
        outgoing_recv: tokio::sync::mpsc::Receiver<OutgoingMessage>,
        config: TransportConfiguration,
    ) -> Result<TcpTransport, Error> {
        let url = self.endpoint.endpoint_url.as_ref().to_string();
        StreamConnector::new(connect_tcp, url)
            .connect(channel, outgoing_recv, config)
            .await
    }

    fn default_endpoint(&self) -> EndpointDescription {
        self.endpoint.clone()
    }
}

async fn connect_tcp(
    endpoint_url: String,
    decoding_options: DecodingOptions,
) -> Result<StreamConnection<ReadHalf<TcpStream>, WriteHalf<TcpStream>>, Error> {
    let bad_url = |e| Error::new(e, format!("{endpoint_url}: no host and port"));
    let (host, port) = hostname_port_from_url(
        &endpoint_url,
        opcua::core::constants::DEFAULT_OPC_UA_SERVER_PORT,
    )
    .map_err(bad_url)?;
    let socket = TcpStream::connect((host.as_str(), port))
        .await
        .map_err(|e| {
            Error::new(
                StatusCode::BadCommunicationError,
                format!("connecting to {host}:{port}: {e}"),
            )
        })?;
    socket.set_nodelay(true).map_err(|e| {
        Error::new(
            StatusCode::BadCommunicationError,
            format!("TCP_NODELAY on {host}:{port}: {e}"),
        )
    })?;
    let (reader, writer) = tokio::io::split(socket);
    Ok(StreamConnection::new(
        FramedRead::new(reader, TcpCodec::new(decoding_options)),
        writer,
        endpoint_url,
    ))
}
