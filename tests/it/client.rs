//! The Modbus client's link handling over real loopback sockets, on tokio's paused clock: the back-off after a
//! failed connect doubles to its cap, no attempt is made while it runs, and a server that comes back is reached
//! within the cap. Virtual time: no real waiting, and the waits are exact.

use std::time::Duration;

use hydrolens::modbus::client::{BACKOFF_CAP, BACKOFF_START, ClientError, DriveClient};
use hydrolens::modbus::map::Table;

use crate::support;

#[tokio::test(start_paused = true)]
async fn the_back_off_doubles_to_its_cap_and_a_returning_server_is_reached_within_it() {
    // a loopback port nothing listens on (bound, noted, closed)
    let port = std::net::TcpListener::bind("127.0.0.1:0").expect("bind").local_addr().expect("addr").port();
    let mut client = DriveClient::new(&format!("127.0.0.1:{port}"), 1, Duration::from_millis(100));
    let mut waits = Vec::new();
    for _ in 0..6 {
        let e = client.read(Table::Input, 0, 6).await.expect_err("nothing listens");
        assert!(matches!(e, ClientError::Connect { .. }), "{e}");
        // the next call does not touch the network: it says how long is left
        match client.read(Table::Input, 0, 6).await {
            Err(ClientError::Backoff(wait)) => waits.push(wait),
            other => panic!("expected a back-off, got {other:?}"),
        }
        tokio::time::advance(*waits.last().expect("a wait")).await;
    }
    let ms = |n| Duration::from_millis(n);
    assert_eq!(BACKOFF_START, ms(50));
    assert_eq!(waits, [ms(50), ms(100), ms(200), ms(400), BACKOFF_CAP, BACKOFF_CAP], "doubling to the cap");
    assert!(!client.is_connected());
    assert_eq!(client.reconnects, 0);

    // one more failure, then the server comes back on that port while the client waits out the cap
    client.read(Table::Input, 0, 6).await.expect_err("still nothing");
    let (_sim, _, stop, task) = support::start_sim(support::test_plant(0.0), port).await;
    let Err(ClientError::Backoff(wait)) = client.read(Table::Input, 0, 6).await else { panic!("backing off") };
    assert!(wait <= BACKOFF_CAP, "{wait:?}");
    tokio::time::advance(wait).await;
    let words = client.read(Table::Input, 0, 6).await.expect("reached within the cap");
    assert_eq!(words.len(), 6);
    assert!(client.is_connected());
    // a good poll forgets the back-off: the next failure waits BACKOFF_START again
    client.good_poll();
    stop.cancel();
    tokio::time::timeout(Duration::from_secs(5), task).await.expect("the simulator stops").expect("joins");
    client.close().await;
    let e = client.read(Table::Input, 0, 6).await.expect_err("the server is gone");
    assert!(matches!(e, ClientError::Connect { .. } | ClientError::Transport(_)), "{e}");
    let Err(ClientError::Backoff(wait)) = client.read(Table::Input, 0, 6).await else { panic!("backing off") };
    assert_eq!(wait, BACKOFF_START);
}
